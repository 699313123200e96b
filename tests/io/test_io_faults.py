"""Hostile inputs at read time: image names no result file can hold, a lens no camera has, an
image far too large for the walk (skipped by its header, never decoded), a video cut short."""
from __future__ import annotations

import json
import logging
import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from scene_helpers import scene_on_disk
from stereoseed.cli import main
from stereoseed.errors import StereoseedError
from stereoseed.geometry.lens import lens_problem
from stereoseed.io import sequence
from stereoseed.io.files import list_images, read_calibration
from stereoseed.io.sequence import header_size
from stereoseed.io.video import read_keyframes


def refused(call, start: str, *says: str) -> str:
    with pytest.raises(StereoseedError) as e:
        call()
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and msg.startswith(start), msg
    for s in says:
        assert s in msg, msg
    return msg


def png(path: Path, width: int = 8, height: int = 6) -> Path:
    # written by Python, not cv2.imwrite: OpenCV crashes on a path holding surrogates
    path.write_bytes(cv2.imencode(".png", np.full((height, width, 3), 90, np.uint8))[1].tobytes())
    return path


# --- 7. names no result file can hold ------------------------------------------------------------
@pytest.mark.parametrize("name, says", [("a\nb.png", "line break"), ("a\rb.png", "line break"),
                                        ("a\u2028b.png", "line break"), ("a\x1bb.png", "control character")])
def test_an_image_name_no_result_can_hold_is_refused_where_it_is_listed(tmp_path, name, says):
    png(tmp_path / "ok.png")
    png(tmp_path / name)
    refused(lambda: list_images(tmp_path), str(tmp_path), says, "rename")
    if "\n" not in name and "\r" not in name and "\u2028" not in name:  # a list file can name it on one line
        (tmp_path / "list.txt").write_text(f"ok.png\n{name}\n", encoding="utf-8")
        refused(lambda: list_images(tmp_path / "list.txt"), f"{tmp_path / 'list.txt'}:2", says)


@pytest.mark.skipif(os.uname().sysname == "Darwin", reason="macOS file names are UTF-8 only")
def test_a_name_of_bytes_that_are_not_utf8_is_refused(tmp_path):
    png(tmp_path / "ok.png")
    png(Path(os.fsdecode(os.fsencode(str(tmp_path)) + b"/caf\xe9.png")))
    refused(lambda: list_images(tmp_path), str(tmp_path), "not UTF-8")


def test_a_run_on_a_folder_with_such_a_name_is_one_line_and_writes_nothing(tmp_path, small_box_scene, capsys):
    paths, calib = scene_on_disk(small_box_scene.prefix(3), tmp_path, images=tmp_path / "images")
    os.rename(paths["images"][2], tmp_path / "images" / "img_002\n.png")
    code = main(["reconstruct", str(tmp_path / "images"), "--calib", str(calib), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("stereoseed: error: ") and err.count("\n") == 1 and "img_002\\n.png" in err
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o*"))


# --- 8. a lens no camera has --------------------------------------------------------------------------
K = np.array([[400.0, 0.0, 159.5], [0.0, 400.0, 119.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("d, name", [([50, 0, 0, 0, 0], "k1"), ([-50, 0, 0, 0, 0], "k1"), ([0, 0, 30, 0, 0], "p1"),
                                     ([-0.1, 0, 0, 0, -400], "k3"), ([0, -30, 0, 0], "k2")])
def test_a_lens_that_folds_or_tears_the_image_is_refused_naming_the_coefficient(tmp_path, d, name):
    assert lens_problem(d, K, (320, 240)) is not None
    P = K @ np.hstack([np.eye(3), [[0.0], [0.0], [1.0]]])
    cams = [{"P": P.tolist(), "K": K.tolist(), "distortion": d, "image_size": [320, 240]}] * 2
    (tmp_path / "calib.json").write_text(json.dumps({"cameras": cams}))
    refused(lambda: read_calibration(tmp_path / "calib.json"), f"{tmp_path / 'calib.json'}: camera 0",
            f"{name} = ", "distortion")


@pytest.mark.parametrize("d", [[-0.28, 0.09, 0.001, -0.0005, -0.01], [0.15, -0.05, 0, 0], [-0.05, 0, 0, 0, 0],
                               [0, 0, 0, 0, 0]])
def test_the_lenses_of_real_cameras_are_accepted(d):
    # a wide angle (corners at r = 0.5 here, 0.9 for the wide one) to a mild pincushion
    assert lens_problem(d, K, (320, 240)) is None
    assert lens_problem(d, np.diag([200.0, 200.0, 1.0]) + [[0, 0, 159.5], [0, 0, 119.5], [0, 0, 0]], (320, 240)) is None


def test_without_an_image_size_the_lens_is_judged_over_the_frame_around_the_principal_point(tmp_path):
    P = K @ np.hstack([np.eye(3), [[0.0], [0.0], [1.0]]])
    (tmp_path / "calib.json").write_text(json.dumps({"cameras": [{"P": P.tolist(), "distortion": [50, 0, 0, 0]}] * 2}))
    refused(lambda: read_calibration(tmp_path / "calib.json"), str(tmp_path / "calib.json"), "k1 = 50")


# --- 9. an image far too large, skipped by its header ----------------------------------------------------
def _png_header_only(path: Path, width: int, height: int) -> Path:
    """A PNG whose header announces width x height and whose pixels are cut short (decoding it
    would fail; reading its header is enough to skip it)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + b"\0\0\0\0IDAT")
    return path


def test_image_headers_give_the_size_the_decoder_gives(tmp_path):
    rng = np.random.default_rng(0)
    for w, h in ((17, 9), (320, 240), (1, 1)):
        image = (rng.random((h, w, 3)) * 255).astype(np.uint8)
        for ext, params in ((".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
                            (".bmp", [])):
            f = tmp_path / f"i{w}{ext}"
            assert cv2.imwrite(str(f), image, params)
            assert header_size(f) == (None if ext == ".bmp" else (w, h)), (f, params)
    assert header_size(_png_header_only(tmp_path / "big.png", 8000, 6000)) == (8000, 6000)
    data = (tmp_path / "i17.jpg").read_bytes()
    for cut in (2, 5, 30):
        (tmp_path / "cut.jpg").write_bytes(data[:cut])
        assert header_size(tmp_path / "cut.jpg") is None
    assert header_size(tmp_path / "missing.png") is None


def test_an_image_too_large_to_decode_is_refused_by_its_header(tmp_path, capsys, monkeypatch):
    """Issue 48 row 8: a small PNG announcing 20000 x 20000 pixels, given as a pair image or to
    `match`, was decoded (memory without bound, then a MemoryError traceback); now refused in
    one line by its header, the decoder never called. A JPEG's frame header counts too."""
    from cli_helpers import one_line_error
    from stereoseed.io.files import read_image

    def no_decoding(*args):
        raise AssertionError("decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    big = _png_header_only(tmp_path / "big.png", 20000, 20000)
    refused(lambda: read_image(big), f"{big}: 20000x20000 pixels (400 MP), more than the 120 MP", "scale it down")
    jpeg = tmp_path / "big.jpg"  # SOI, then a baseline frame header of 12000 x 11000
    jpeg.write_bytes(b"\xff\xd8\xff\xc0" + struct.pack(">HBHH", 11, 8, 11000, 12000) + b"\x03\x01\x11\x00")
    refused(lambda: read_image(jpeg), f"{jpeg}: 12000x11000 pixels (132 MP)")
    code = main(["match", str(big), str(jpeg)])
    err = capsys.readouterr().err
    assert code == 2 and one_line_error(err) and f"{big}: 20000x20000 pixels" in err


def test_an_image_of_another_size_is_skipped_by_its_header_never_decoded(tmp_path, small_box_scene, monkeypatch):
    from stereoseed.pipeline import reconstruct_to_folder

    paths, calib = scene_on_disk(small_box_scene.prefix(4), tmp_path, images=tmp_path / "images")
    big = _png_header_only(tmp_path / "images" / "huge.png", 8000, 6000)
    images = list(paths["images"])
    (tmp_path / "list.txt").write_text("".join(f"{p}\n" for p in images[:3] + [big] + images[3:]))
    decoded = []
    real = sequence.read_image
    monkeypatch.setattr(sequence, "read_image", lambda p: decoded.append(Path(p).name) or real(p))
    report = reconstruct_to_folder(str(tmp_path / "list.txt"), str(calib), tmp_path / "o")
    assert "huge.png" not in decoded
    skipped = report["per_image"][3]
    assert skipped["status"] == "failed" and "8000x6000" in skipped["reason"], skipped
    assert report["registered"] == 4
    cams = json.loads((tmp_path / "o" / "cameras.json").read_text())["images"][3]
    assert (cams["width"], cams["height"], cams["registered"]) == (8000, 6000, False)


# --- 9. a video cut short ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def walk_video(tmp_path_factory):
    from scene_helpers import write_video
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    frames = render_scene(SceneConfig(n_images=40, step_deg=2.0, azimuth0_deg=50.0, focal_px=400, focal0_px=400,
                                      principal_offset0_px=(0.0, 0.0), focal_jitter=0.0, pose_jitter=False,
                                      width=320, height=240, supersample=1, seed=4))
    return write_video(tmp_path_factory.mktemp("video") / "walk.avi", frames.images)


def test_a_video_cut_short_says_so_and_keeps_the_decoder_off_the_terminal(walk_video, tmp_path, caplog, capfd,
                                                                         monkeypatch):
    # a handler an in-process run of the command left behind writes to a stream that is gone
    monkeypatch.setattr(logging.getLogger("stereoseed"), "handlers", [])
    data = walk_video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(0.7 * len(data))])
    capfd.readouterr()
    with caplog.at_level(logging.WARNING, logger="stereoseed.io.video"):
        keyframes = read_keyframes(cut)
    assert keyframes
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "of the 40 frames the file announces" in warned[0], warned
    assert capfd.readouterr().err == ""  # FFmpeg's own lines are captured, quoted in the warning at most
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stereoseed.io.video"):
        read_keyframes(walk_video)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]  # a whole video: nothing to say
