"""The nesting bound read before a parser recurses (issue 48 row 6): real files pass, deep ones not."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.io.nesting import MAX_NESTING, nesting_depth, read_bounded_text

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.parametrize("text, depth", [
    ('{"a": [[1, 2], [3]], "b": "[[[[not nested]]]]"}', 3),  # a string's brackets do not count
    ("%YAML:1.0\nm: !!opencv-matrix\n  rows: 1\n  data: [ 1., 2. ]\n", 1),
    ("a:\n  - - - x\n", 3),
    ("<opencv_storage><m type_id='x'><rows>1</rows><data/></m></opencv_storage>", 3),
    ("", 0),
])
def test_nesting_depth(text, depth):
    assert nesting_depth(text) == depth


def test_real_calibration_and_target_files_are_far_below_the_bound(tmp_path):
    for target in EXAMPLES.glob("*/target.json"):
        assert nesting_depth(target.read_text()) <= 6
    for ext in ("yaml", "xml", "json"):
        path = tmp_path / f"cam.{ext}"
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", np.eye(3))
        fs.write("distortion_coefficients", np.zeros((1, 5)))
        fs.release()
        assert nesting_depth(read_bounded_text(path, "calibration file", "")) <= 3 < MAX_NESTING


def test_a_file_too_large_or_too_deep_is_refused_in_one_line(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * (MAX_NESTING + 1) + "]" * (MAX_NESTING + 1))
    with pytest.raises(StereoseedError, match=rf"^{deep}: nested {MAX_NESTING + 1} levels deep.*; give another"):
        read_bounded_text(deep, "target file", "give another")
    big = tmp_path / "big.json"
    with open(big, "wb") as f:
        f.truncate(5 * 2**20)
    with pytest.raises(StereoseedError, match="too large for a target file"):
        read_bounded_text(big, "target file", "give another")
