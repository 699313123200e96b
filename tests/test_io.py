import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from stereoseed.errors import StereoseedError
from stereoseed.io import (list_images, read_calibration, read_image, read_ply, read_points_file,
                           write_json, write_ply)


def test_points_file_reader(tmp_path):
    f = tmp_path / "p.txt"
    f.write_text("# X Y Z\n1 2 3\n\n4,5,6  # comment\n")
    np.testing.assert_array_equal(read_points_file(f, 3), [[1, 2, 3], [4, 5, 6]])
    f.write_text("1 2\n")
    with pytest.raises(StereoseedError, match="expected 3 numbers a line, found 2"):
        read_points_file(f, 3)
    f.write_text("1 2 nan\n")
    with pytest.raises(StereoseedError, match="NaN"):
        read_points_file(f, 3)
    with pytest.raises(StereoseedError, match="not found"):
        read_points_file(tmp_path / "missing.txt", 3)


@settings(max_examples=80, deadline=None)
@given(st.text(max_size=200))
def test_points_reader_never_crashes(tmp_path_factory, text):
    f = tmp_path_factory.mktemp("r") / "p.txt"
    f.write_text(text)
    try:
        pts = read_points_file(f, 2)
    except StereoseedError as e:
        assert str(e).startswith(str(f))
    else:
        assert pts.shape[1] == 2 and np.all(np.isfinite(pts))


def test_calibration_json_only_P_required(tmp_path):
    P = np.hstack([np.diag([800.0, 800.0, 1.0]), np.array([[1.0], [2.0], [3.0]])])
    f = tmp_path / "calib.json"
    f.write_text(json.dumps({"cameras": [{"P": P.tolist()}, {"P": (2 * P).tolist()}]}))
    P1, P2 = read_calibration(f)
    np.testing.assert_array_equal(P1, P)
    f.write_text(json.dumps({"cameras": [{"P": [[1, 2, 3]]}, {"P": P.tolist()}]}))
    with pytest.raises(StereoseedError, match="3x4"):
        read_calibration(f)
    f.write_text("{not json")
    with pytest.raises(StereoseedError, match="not valid JSON"):
        read_calibration(f)


def test_middlebury_par_lookup(tmp_path):
    K = "800 0 320 0 800 240 0 0 1"
    R = "1 0 0 0 1 0 0 0 1"
    f = tmp_path / "x_par.txt"
    f.write_text(f"2\na.png {K} {R} 0 0 1\nb.png {K} {R} 0.1 0 1\n")
    Pa, Pb = read_calibration(f, ["a.png", "b.png", "c.png"])
    assert Pb[0, 3] == pytest.approx(80.0 + 320.0)
    with pytest.raises(StereoseedError, match="no camera for image 'z.png'"):
        read_calibration(f, ["z.png", "a.png"])


def test_images_and_lists(tmp_path):
    import cv2
    img = (np.random.default_rng(0).random((20, 30, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "b.png"), img)
    cv2.imwrite(str(tmp_path / "a.ppm"), img)
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in list_images(tmp_path)] == ["a.ppm", "b.png"]
    lst = tmp_path / "list.txt"
    lst.write_text("b.png\n# comment\na.ppm\n")
    assert [p.name for p in list_images(lst)] == ["b.png", "a.ppm"]
    np.testing.assert_array_equal(read_image(tmp_path / "b.png"), img)
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(StereoseedError, match="not a readable image"):
        read_image(tmp_path / "bad.png")
    lst.write_text("b.png\nmissing.png\n")
    with pytest.raises(StereoseedError, match="missing.png"):
        list_images(lst)


def test_ply_roundtrip_and_atomic_json(tmp_path):
    pts = np.random.default_rng(1).normal(size=(100, 3))
    cols = np.random.default_rng(2).integers(0, 255, (100, 3)).astype(np.uint8)
    write_ply(tmp_path / "deep" / "x.ply", pts, cols)
    p2, c2 = read_ply(tmp_path / "deep" / "x.ply")
    np.testing.assert_allclose(p2, pts, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(c2, cols)
    header = (tmp_path / "deep" / "x.ply").read_bytes()[:200]
    assert b"binary_little_endian" in header and b"property uchar red" in header
    write_json(tmp_path / "r.json", {"a": np.arange(3), "b": np.float32(1.5)})
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": [0, 1, 2], "b": 1.5}
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary file left behind
