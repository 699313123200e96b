import json
import re

import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.io.files import list_images, read_calibration, read_image, read_middlebury_par, read_points_file, write_json
from stereoseed.io.ply import read_ply, write_ply


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


# ---------------------------------------------------------------- hostile inputs: one line, the path, what to do
ACTION = re.compile(r"\b(give|check|fix|save|extract|keep|rescale|export)\b")
P_OK = np.hstack([np.diag([800.0, 800.0, 1.0]), np.array([[1.0], [2.0], [3.0]])])
K_TXT, R_TXT = "800 0 320 0 800 240 0 0 1", "1 0 0 0 1 0 0 0 1"


def refused(call, path, *fragments):
    """``call()`` raises a StereoseedError of one line that starts with ``path``, holds every
    fragment and says what to do; returns the message."""
    with pytest.raises(StereoseedError) as info:
        call()
    msg = str(info.value)
    assert len(msg.splitlines()) == 1, msg
    assert msg.startswith(str(path)), msg
    assert ACTION.search(msg), msg
    for f in fragments:
        assert f in msg, msg
    return msg


def write_png(path, shape=(20, 30, 3), value=None):
    import cv2
    img = (np.random.default_rng(0).random(shape) * 255).astype(np.uint8) if value is None else np.full(shape, value, np.uint8)
    assert cv2.imwrite(str(path), img)
    return img


# case 1: P with a singular (or near-singular) left block, non-finite or absurd values
@pytest.mark.parametrize("P, fragment", [
    (np.zeros((3, 4)), "all zeros"),
    (np.hstack([np.zeros((3, 3)), np.ones((3, 1))]), "singular"),
    (np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 1]]), "singular"),          # rank 2
    (np.array([[1e3, 0, 0, 0], [0, 1e3, 0, 0], [0, 0, 1e-9, 1]]), "singular"),      # cond 1e12
    (P_OK * 1e-120, "out of range"),
    (P_OK * 1e120, "out of range"),
], ids=["zero", "zero-block", "rank2", "near-singular", "tiny", "huge"])
def test_singular_or_absurd_P_refused(tmp_path, P, fragment):
    f = tmp_path / "calib.json"
    f.write_text(json.dumps({"cameras": [{"P": P.tolist()}, {"P": P_OK.tolist()}]}))
    refused(lambda: read_calibration(f), f, "camera 0", fragment)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_P_singularity_test_is_scale_free(tmp_path, scale):
    f = tmp_path / "calib.json"
    P = P_OK * scale
    f.write_text(json.dumps({"cameras": [{"P": P.tolist()}, {"P": P.tolist()}]}))
    np.testing.assert_array_equal(read_calibration(f)[0], P)


# case 2: list_images with an image, a video, other encodings, non-ASCII names
def test_list_images_refuses_an_image_or_a_video(tmp_path):
    write_png(tmp_path / "a.png")
    refused(lambda: list_images(tmp_path / "a.png"), tmp_path / "a.png", "is an image", "folder")
    (tmp_path / "frame").write_bytes((tmp_path / "a.png").read_bytes())  # an image without extension
    refused(lambda: list_images(tmp_path / "frame"), tmp_path / "frame", "PNG image", "folder")
    (tmp_path / "clip.mp4").write_bytes(b"\0\0\0 ftypisom")
    refused(lambda: list_images(tmp_path / "clip.mp4"), tmp_path / "clip.mp4", "video", "ffmpeg")
    (tmp_path / "junk.txt").write_bytes(bytes(range(256)))
    refused(lambda: list_images(tmp_path / "junk.txt"), tmp_path / "junk.txt", "binary")
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    refused(lambda: list_images(tmp_path / "empty.txt"), tmp_path / "empty.txt", "no image paths")


@pytest.mark.parametrize("encoding", ["utf-8", "utf-8-sig", "latin-1", "utf-16"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_list_file_encodings_and_non_ascii_names(tmp_path, encoding, newline):
    names = ["café.png", "b.png"] + (["日本語.png"] if encoding not in ("latin-1",) else [])
    for n in names:
        write_png(tmp_path / n)
    lst = tmp_path / "list.txt"
    lst.write_bytes(newline.join(["# the sequence"] + names + [""]).encode(encoding))
    assert [p.name for p in list_images(lst)] == names


def test_list_file_missing_image_names_line_and_escapes(tmp_path):
    write_png(tmp_path / "a.png")
    lst = tmp_path / "list.txt"
    lst.write_text("a.png\n\nb\u2028c.png\nd.png\n", encoding="utf-8")
    msg = refused(lambda: list_images(lst), lst, ":3: listed image not found", "(and 1 more)")
    assert "\\u2028" in msg  # shown escaped, the message stays one line


# case 3: calibration format by content
def test_calibration_format_by_content(tmp_path):
    f = tmp_path / "calib.txt"  # a calib.json named .txt
    f.write_text(json.dumps({"cameras": [{"P": P_OK.tolist()}, {"P": P_OK.tolist()}]}))
    np.testing.assert_array_equal(read_calibration(f)[1], P_OK)
    g = tmp_path / "cams.json"  # a par file named .json
    g.write_text(f"2\na.png {K_TXT} {R_TXT} 0 0 1\nb.png {K_TXT} {R_TXT} 1 0 1\n")
    assert read_calibration(g, ["a.png", "b.png"])[1][0, 3] == pytest.approx(800 + 320)


@pytest.mark.parametrize("content, fragment", [
    (bytes(range(256)) * 4, "binary content"),
    ("2\ncafé.png 1 2\n".encode("latin-1"), "not UTF-8 text (byte 0xe9"),
    (b"", "empty file"),
    (b"  \n\n", "empty file"),
    (b"%YAML 1.2\nK: [1, 2]\n", "neither JSON nor a Middlebury par file"),
    (b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR", "PNG image"),
], ids=["binary", "latin-1", "empty", "blank", "yaml", "png"])
def test_calibration_undecodable_or_unknown(tmp_path, content, fragment):
    f = tmp_path / "x_par.txt"
    f.write_bytes(content)
    refused(lambda: read_calibration(f, ["a.png", "b.png"]), f, fragment, "calib.json", "COLMAP")


def test_calibration_missing_and_colmap_folder(tmp_path):
    refused(lambda: read_calibration(tmp_path / "nope.json"), tmp_path / "nope.json", "not found")
    with pytest.raises(StereoseedError, match="not a COLMAP model"):  # export.py's message
        read_calibration(tmp_path, ["a.png", "b.png"])


# case 4: point files
@pytest.mark.parametrize("content, expected", [
    ("\ufeff1 2\n3 4\n".encode("utf-8"), [[1, 2], [3, 4]]),                 # BOM
    (b"1 2\r\n3,4\r\n", [[1, 2], [3, 4]]),                                  # Windows line ends
    (b"1 2\r3 4\r", [[1, 2], [3, 4]]),                                        # old Mac line ends
    ("# Maß in mm\n1 2\n".encode("latin-1"), [[1, 2]]),                      # Latin-1 comment
    ("1 2\n-3.5e2 +.5\n".encode("utf-16"), [[1, 2], [-350, 0.5]]),           # UTF-16 with BOM
])
def test_points_file_encodings(tmp_path, content, expected):
    f = tmp_path / "pixels.txt"
    f.write_bytes(content)
    np.testing.assert_array_equal(read_points_file(f, 2), expected)


@pytest.mark.parametrize("content, fragment", [
    (b"1 2\n1e400 3\n", ":2: 1e400 is out of range"),
    (b"1 2\n-1e101 3\n", ":2: -1e101 is out of range"),
    (b"1 inf\n", ":1: NaN or infinite"),
    (b"1 NaN\n", ":1: NaN or infinite"),
    (b"1_0 2\n", ":1: not a number: 1_0"),
    ("\u0661 2\n".encode(), ":1: not a number"),                              # an Arabic-Indic digit
    (b"1 2 3\n", ":1: expected 2 numbers a line, found 3"),
    (b"", "no points"),
    (b"# only a comment\r\n", "no points"),
    (bytes(range(256)), "binary content"),
    (b"\xff\xd8\xff\xe0\0\x10JFIF", "JPEG image"),
], ids=["1e400", "1e101", "inf", "nan", "underscore", "arabic", "count", "empty", "comment", "binary", "jpeg"])
def test_points_file_refusals(tmp_path, content, fragment):
    f = tmp_path / "pixels.txt"
    f.write_bytes(content)
    refused(lambda: read_points_file(f, 2), f, fragment)


def test_points_file_is_a_folder(tmp_path):
    refused(lambda: read_points_file(tmp_path, 3), tmp_path, "is a folder")


# case 5: Middlebury par files
@pytest.mark.parametrize("content, fragment", [
    (bytes(range(256)), "binary content"),
    (f"2\na.png {K_TXT} {R_TXT} 0 0\n".encode(), ":2: a par line holds a name and 21 numbers, found 21"),
    (f"3\na.png {K_TXT} {R_TXT} 0 0 1\nb.png {K_TXT} {R_TXT} 0 0 1\n".encode(), "count line says 3 cameras but 2"),
    (f"two\na.png {K_TXT} {R_TXT} 0 0 1\n".encode(), ":1: the count line must be a whole number"),
    (f"1\na.png {K_TXT} {R_TXT} 0 0 nan\n".encode(), ":2: NaN or infinite"),
    (f"1\na.png {K_TXT} {R_TXT} 0 0 1e999\n".encode(), ":2: 1e999 is out of range"),
    (f"1\na.png 0 0 0 0 0 0 0 0 0 {R_TXT} 0 0 1\n".encode(), ":2: K of a.png is singular"),
    (f"1\na.png 800 0 320 1600 0 640 0 0 1 {R_TXT} 0 0 1\n".encode(), ":2: K of a.png is singular"),
    (f"1\na.png {R_TXT} {K_TXT} 0 0 1\n".encode(), ":2: R of a.png is not a rotation"),
    (f"2\na.png {K_TXT} {R_TXT} 0 0 1\n\na.png {K_TXT} {R_TXT} 0 0 1\n".encode(), ":4: image 'a.png' is given twice"),
    (b"0\n", "no cameras"),
], ids=["binary", "fields", "count", "count-word", "nan", "overflow", "K-zero", "K-rank2", "R", "twice", "none"])
def test_par_file_refusals(tmp_path, content, fragment):
    f = tmp_path / "x_par.txt"
    f.write_bytes(content)
    refused(lambda: read_middlebury_par(f), f, fragment)
    refused(lambda: read_calibration(f, ["a.png", "b.png"]), f)


def test_par_file_bom_crlf_and_real_file(tmp_path):
    f = tmp_path / "x_par.txt"
    f.write_bytes(f"\ufeff2\r\na.png {K_TXT} {R_TXT} 0 0 1\r\nb.png {K_TXT} {R_TXT} 0.1 0 1\r\n".encode())
    assert set(read_middlebury_par(f)) == {"a.png", "b.png"}
    from pathlib import Path
    real = Path("/work/shared/data/templeSparseRing/templeSR_par.txt")
    if real.is_file():
        assert len(read_middlebury_par(real)) == 16


# case 6: images OpenCV cannot decode, without noise on stderr
def _damaged(tmp_path):
    import cv2
    write_png(tmp_path / "ok.png", (60, 80, 3))
    png = (tmp_path / "ok.png").read_bytes()
    jpg = cv2.imencode(".jpg", np.zeros((60, 80, 3), np.uint8) + 90)[1].tobytes()
    crc = bytearray(png)
    crc[len(png) // 2] ^= 0xFF
    return {"truncated.png": (png[: len(png) // 2], "truncated PNG"), "header.png": (png[:40], "PNG"),
            "crc.png": (bytes(crc), "PNG"), "truncated.jpg": (jpg[: len(jpg) // 2], "JPEG"),
            "text.png": (b"hello, not an image\n", "not an image format"), "empty.png": (b"", "empty file")}


def test_read_image_damaged_files_one_line_and_quiet(tmp_path, capfd):
    for name, (data, fragment) in _damaged(tmp_path).items():
        (tmp_path / name).write_bytes(data)
        capfd.readouterr()
        msg = refused(lambda: read_image(tmp_path / name), tmp_path / name, fragment)
        out, err = capfd.readouterr()
        assert (out, err) == ("", ""), (name, msg, err)


def test_read_image_black_flat_grey_and_non_ascii_are_images(tmp_path):
    write_png(tmp_path / "black.png", value=0)
    write_png(tmp_path / "white.png", (7, 5), value=255)  # grey levels -> BGR
    write_png(tmp_path / "été.png")
    assert read_image(tmp_path / "black.png").shape == (20, 30, 3)
    assert read_image(tmp_path / "white.png").shape == (7, 5, 3)
    assert read_image(tmp_path / "été.png").dtype == np.uint8
    refused(lambda: read_image(tmp_path), tmp_path, "is a folder")
    refused(lambda: read_image(tmp_path / "none.png"), tmp_path / "none.png", "not found")


# case 7: calib.json of the wrong shape
@pytest.mark.parametrize("text, fragment", [
    ('{"cameras": ["x", {"P": 1}]}', "camera 0 has no 'P' (it is a string)"),
    ('{"cameras": [[1, 2], {"P": 1}]}', "camera 0 has no 'P' (it is a list of 2)"),
    ('{"cameras": [{"K": 1}, {"P": 1}]}', "camera 0 has no 'P'"),
    ('{"cameras": [{"P": [[1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "rows of 3/4/4 items, not a 3x4"),
    ('{"cameras": [{"P": [[1, 0, 0, 0], [0, 1, 0, 0]]}, {}]}', "3x4"),
    ('{"cameras": [{"P": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]}, {}]}', "3x4"),
    ('{"cameras": [{"P": [[[1], 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "holds a list of 1"),
    ('{"cameras": [{"P": [["1", "0", "0", "0"], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "holds a string"),
    ('{"cameras": [{"P": [[true, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "holds true"),
    ('{"cameras": [{"P": [[null, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "holds null"),
    ('{"cameras": [{"P": [[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "NaN or infinite"),
    ('{"cameras": [{"P": [[Infinity, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "NaN or infinite"),
    ('{"cameras": [{"P": [[1e400, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "NaN or infinite"),
    ('{"cameras": [{"P": [[1' + "0" * 400 + ', 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "out of range"),
    ('{"cameras": [{"P": [[1' + "0" * 5000 + ', 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, {}]}', "not a JSON"),
    ('{"cameras": {"a": 1}}', 'no "cameras" list (it is an object)'),
    ('{"Cameras": []}', 'no "cameras" list;'),
    ('{"cameras": [{"P": 1}]}', "holds 1 camera(s)"),
    ("[1, 2, 3]", "the JSON is a list of 3, not an object"),
    ('"cameras"', "neither JSON nor"),
    ("[" * 100000 + "]" * 100000, "not a JSON"),
    ('{"cameras": [' + "[" * 50000 + "]" * 50000 + "]}", "not a JSON"),
    ('{"cameras": [{"P": 1}, {"P": 2}]', "not valid JSON"),
], ids=lambda v: v[:30] if isinstance(v, str) else None)
def test_calibration_json_structure(tmp_path, text, fragment):
    f = tmp_path / "calib.json"
    f.write_text(text)
    refused(lambda: read_calibration(f), f, fragment)


def test_colmap_model_that_cannot_be_read_is_one_line(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 800 800 320 240\n")
    (tmp_path / "images.txt").write_text("1 0 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 1 b.png\n\n")  # zero quaternion
    refused(lambda: read_calibration(tmp_path, ["a.png", "b.png"]), tmp_path, "cannot be read", "export it again")
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 0 0 320 240\n")  # zero focal length
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 1 b.png\n\n")
    refused(lambda: read_calibration(tmp_path, ["a.png", "b.png"]), tmp_path, "a.png: 'P' is not a camera")


def test_text_starting_like_an_ascii_pnm_is_still_text(tmp_path):
    f = tmp_path / "x_par.txt"  # an image named "P1", with integer K: not a PNM header
    f.write_text(f"P1 {K_TXT} {R_TXT} 0 0 1\nb.png {K_TXT} {R_TXT} 1 0 1\n")
    assert read_calibration(f, ["P1", "b.png"])[0].shape == (3, 4)
    g = tmp_path / "frames"
    g.write_bytes(b"P2\n4 3\n255\n" + b"0 " * 12)  # a text PGM without extension
    refused(lambda: list_images(g), g, "PNM image")


def test_images_read_in_threads_leave_stderr_where_it_was(tmp_path, capfd):
    """The mapper reads images in background threads while the main thread reads others: each
    read routes file descriptor 2 to a file for a moment, and overlapping routings used to
    restore each other's file, losing the run's stderr (progress bars, error lines) for good."""
    import os
    import threading

    import cv2

    path = tmp_path / "a.png"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8))
    before = os.fstat(2)

    def read_many():
        for _ in range(40):
            read_image(path)

    threads = [threading.Thread(target=read_many) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
    os.write(2, b"still here\n")
    assert "still here" in capfd.readouterr().err


def test_a_file_name_near_the_file_systems_limit_is_written(tmp_path):
    """Issue 48 row 12: the temporary name of an atomic write ('.NAME.xxxxxxxx.tmp.png') of an
    image named near 255 bytes was too long, so the hand-off exports failed after reconstruct
    had taken the name. Names of 255 bytes (one of two-byte characters) are written."""
    from stereoseed.io.atomic import NAME_MAX, write_text
    from stereoseed.io.files import write_image

    for name in ("a" * (NAME_MAX - 4) + ".png", "é" * ((NAME_MAX - 5) // 2) + "x.png"):
        assert len(name.encode()) == NAME_MAX
        write_image(tmp_path / name, np.zeros((4, 4, 3), np.uint8))
        assert (tmp_path / name).stat().st_size > 0
    write_text(tmp_path / ("t" * NAME_MAX), "text")
    assert [len(p.name.encode()) for p in tmp_path.iterdir()] == [NAME_MAX] * 3  # no temporary file left


def test_a_ply_written_in_chunks_is_the_ply_written_at_once(tmp_path, monkeypatch):
    """A large cloud's rows are put together a chunk at a time (memory): the file is the same,
    byte for byte, as the rows written at once, and reads back."""
    from stereoseed.io import ply

    rng = np.random.default_rng(1)
    n = 1000
    points, colors = rng.normal(size=(n, 3)), rng.integers(0, 256, (n, 3)).astype(np.uint8)
    props = {"nx": rng.normal(size=n), "support": rng.integers(2, 9, n)}
    monkeypatch.setattr(ply, "_ROWS_PER_WRITE", 3 * n)
    ply.write_ply(tmp_path / "once.ply", points, colors, props)
    monkeypatch.setattr(ply, "_ROWS_PER_WRITE", 64)
    ply.write_ply(tmp_path / "chunks.ply", points, colors, props)
    assert (tmp_path / "chunks.ply").read_bytes() == (tmp_path / "once.ply").read_bytes()
    vertex = ply.read_ply_vertices(tmp_path / "chunks.ply")
    np.testing.assert_array_equal(vertex["x"], points[:, 0].astype(np.float32))
    np.testing.assert_array_equal(vertex["support"], props["support"])
    # one colour and one value for every vertex, past the first chunk too
    ply.write_ply(tmp_path / "one.ply", points, np.array([10, 20, 30], np.uint8), {"support": np.array([4])})
    vertex = ply.read_ply_vertices(tmp_path / "one.ply")
    assert (vertex["green"] == 20).all() and (vertex["support"] == 4).all() and len(vertex) == n
