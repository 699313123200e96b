"""The writers' rule (issue 48): an existing file at an output of `calibrate` (-o, the target as
found, the check images), `intrinsics`, `match` or `propagate` that stereoseed did not write, or
that changed since, is refused before any work in one line and left byte for byte; one stereoseed
wrote (its record beside it says so, with its hash) is the command's to replace, as before.
(`target` and `export` are tested with their commands: tests/calibration/test_printing.py,
tests/output/test_export_faults.py; `mesh` in tests/dense/test_mesh.py.)"""
from __future__ import annotations

import json
import os

import pytest

from cli_helpers import one_line_error, run
from stereoseed.io.outputs import WRITTEN_RECORD, record_written_file
from stereoseed.synthetic.scene import write_scene

USERS = b"the user's own file, no output of stereoseed\n"


@pytest.fixture(scope="module")
def scene(tmp_path_factory, small_box_scene) -> dict:
    return write_scene(small_box_scene.prefix(2), tmp_path_factory.mktemp("scene"))


def _commands(scene: dict, tmp) -> dict[str, tuple[list, object]]:
    """Per writer: its command line and the output the test puts the user's file at."""
    image1, image2 = scene["images"][:2]
    calib, target = tmp / "calib.json", tmp / "t.json"
    return {
        "calibrate -o": (["calibrate", scene["pattern"], scene["points1"], scene["points2"], "-o", calib], calib),
        "calibrate, the target as found": (["calibrate", "--target", target, image1, image2, "-o", calib],
                                           tmp / "calib_target.json"),
        "calibrate, a check image": (["calibrate", "--target", target, image1, image2, "--lens-images2",
                                      tmp / "shots" / "7.jpg", "-o", calib], tmp / "calib_cam2_7.png"),
        "intrinsics -o": (["intrinsics", image1, "--target", target, "-o", tmp / "camera.yaml"], tmp / "camera.yaml"),
        "match -o": (["match", image1, image2, "-o", tmp / "m.png"], tmp / "m.png"),
        "propagate -o": (["propagate", image1, image2, "--calib", scene["cameras"], "-o", tmp / "d.png"],
                         tmp / "d.png"),
    }


WRITERS = ["calibrate -o", "calibrate, the target as found", "calibrate, a check image", "intrinsics -o", "match -o",
           "propagate -o"]


@pytest.mark.parametrize("writer", WRITERS)
def test_a_users_file_at_a_writers_output_is_refused_and_left_as_it_is(scene, tmp_path, capsys, writer):
    args, mine = _commands(scene, tmp_path)[writer]
    mine.write_bytes(USERS)
    code, _, err = run(capsys, *args)
    assert code == 2 and one_line_error(err), err
    assert f"{mine}: exists and stereoseed did not write it" in err and "remove it yourself" in err, err
    assert mine.read_bytes() == USERS
    assert [p.name for p in tmp_path.iterdir()] == [mine.name]  # nothing else written either


@pytest.mark.parametrize("writer", ["match -o", "calibrate -o"])
def test_a_link_at_a_writers_output_is_refused_and_its_file_left(scene, tmp_path, capsys, writer):
    """A link to the user's file elsewhere: writing through it (or over it) is refused too."""
    args, at = _commands(scene, tmp_path)[writer]
    mine = tmp_path / "elsewhere" / "theirs"
    mine.parent.mkdir()
    mine.write_bytes(USERS)
    at.symlink_to(mine)
    code, _, err = run(capsys, *args)
    assert code == 2 and one_line_error(err) and f"{at}: exists and stereoseed did not write it" in err, err
    assert at.is_symlink() and mine.read_bytes() == USERS


def test_a_writers_own_output_is_replaced_and_one_edited_since_refused(scene, tmp_path, capsys):
    """calibrate -o and match -o replace their own earlier output by default (as they always did);
    once the user edits it, it is theirs: refused, left as edited."""
    commands = _commands(scene, tmp_path)
    for writer in ("calibrate -o", "match -o"):
        args, out = commands[writer]
        assert run(capsys, *args)[0] == 0
        first = os.stat(out)
        recorded = json.loads((tmp_path / WRITTEN_RECORD).read_text())
        assert recorded["written_by"] == "stereoseed" and out.name in recorded["files"]
        assert run(capsys, *args)[0] == 0  # its own: replaced (atomically: a new file)
        assert os.stat(out).st_ino != first.st_ino
        edited = out.read_bytes() + b"\n"
        out.write_bytes(edited)
        code, _, err = run(capsys, *args)
        assert code == 2 and one_line_error(err) and "(or it changed since)" in err, err
        assert out.read_bytes() == edited
    assert sorted(json.loads((tmp_path / WRITTEN_RECORD).read_text())["files"]) == ["calib.json", "m.png"]


@pytest.mark.parametrize("writer", ["calibrate, the target as found", "calibrate, a check image", "intrinsics -o",
                                    "propagate -o"])
def test_a_file_stereoseed_recorded_is_past_the_check(scene, tmp_path, capsys, writer):
    """The writers whose full run needs photos of a target or a calibration: a file the record
    beside it lists, unchanged, is the command's to replace; the command goes on to its inputs
    (here: the next refusal, a target or calibration that is missing)."""
    args, out = _commands(scene, tmp_path)[writer]
    out.write_bytes(b"as stereoseed wrote it")
    record_written_file(out)
    args = [a if a != scene["cameras"] else tmp_path / "none.json" for a in args]
    code, _, err = run(capsys, *args)
    assert code == 2 and "did not write it" not in err and ("not found" in err or "no such" in err.lower()), err


def test_a_record_that_is_no_record_and_the_records_name_are_refused(scene, tmp_path, capsys):
    args, out = _commands(scene, tmp_path)["match -o"]
    (tmp_path / WRITTEN_RECORD).write_bytes(USERS)
    code, _, err = run(capsys, *args)
    assert code == 2 and one_line_error(err) and f"{WRITTEN_RECORD}: is not the record" in err, err
    assert (tmp_path / WRITTEN_RECORD).read_bytes() == USERS and not out.exists()
    args, _ = _commands(scene, tmp_path)["calibrate -o"]
    code, _, err = run(capsys, *args[:-1], tmp_path / "sub" / WRITTEN_RECORD)
    assert code == 2 and one_line_error(err) and "is the name of stereoseed's record" in err, err
