"""Hypothesis fuzzing of every input reader.

The property, for any bytes: a reader returns a valid result (the right shape, finite; a camera
P (3, 4) finite with a non-singular left 3x3 block) or raises a StereoseedError whose message is
one line and starts with the path it was given; never any other exception (and no NumPy warning:
pytest turns RuntimeWarning into an error). Strategies: raw bytes, text with odd characters,
and almost-valid files (valid ones with a token replaced, random shapes and types, encodings,
BOMs and line ends).
"""
import json
import math
import os

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, event, example, given, settings, strategies as st

from stereoseed.errors import StereoseedError
from stereoseed.io.files import (MAX_MAGNITUDE, SINGULAR_RATIO, list_images, read_calibration, read_image,
                           read_middlebury_par, read_points_file)

# STEREOSEED_FUZZ_EXAMPLES=5000 for a longer soak (about 1 minute)
N = int(os.environ.get("STEREOSEED_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=N, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def outcome(call, path):
    """call()'s result, or None after checking its StereoseedError: one line, starting with path."""
    try:
        result = call()
    except StereoseedError as e:
        event("refused")
        msg = str(e)
        assert len(msg.splitlines()) == 1, msg
        assert msg.startswith(str(path)), msg
        return None
    event("valid")
    return result


def assert_camera(P):
    assert isinstance(P, np.ndarray) and P.shape == (3, 4) and P.dtype == np.float64
    assert np.all(np.isfinite(P))
    s = np.linalg.svd(P[:, :3] / np.abs(P[:, :3]).max(), compute_uv=False)
    assert s[2] >= SINGULAR_RATIO * s[0] > 0


# ---------------------------------------------------------------- shared strategies
ODD_CHARS = ["\ufeff", "\u2028", "\u2029", "\x85", "\x00", "\x1b", "\x0c", "\x0b", "\r", "\t", "é", "日", "\U0001F600",
             "\udcff", "٣", "１", "\xa0", "\u200b", "_", "#", ",", ";", "\\", "/", '"', "'", "{", "}", "[", "]"]
odd_text = st.text(st.one_of(st.characters(), st.sampled_from(ODD_CHARS)), max_size=200)
NEWLINES = st.sampled_from(["\n", "\r\n", "\r"])
ENCODINGS = st.sampled_from(["utf-8", "utf-8-sig", "latin-1", "cp1252", "utf-16", "utf-16-le"])


def encoded(text_strategy):
    """Text encoded with a random encoding (unencodable characters replaced or escaped)."""
    return st.builds(lambda t, enc: t.encode(enc, errors="surrogatepass" if enc.startswith("utf") else "replace"),
                     text_strategy, ENCODINGS)


def mutated(text_strategy, tokens):
    """A valid text with one whitespace-separated token replaced (or the text cut short)."""
    def mutate(text, i, token, cut):
        parts = text.split(" ")
        if token is not None:
            parts[i % len(parts)] = token
        text = " ".join(parts)
        return text[:cut] if cut is not None else text
    return st.builds(mutate, text_strategy, st.integers(0, 200), st.one_of(st.none(), tokens),
                     st.one_of(st.none(), st.integers(0, 400)))


number_token = st.one_of(
    st.floats(width=64).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["1e400", "-1e400", "1e-400", "1e100", "1e101", "nan", "NaN", "inf", "-Infinity", "1_0", "0x10",
                     "٣", "１", "+.5", "5.", ".", "-", "e5", "1e", "--1", "1,5", "", "#", "1#2", "\x00", "\ufeff1",
                     "9" * 400, "0." + "0" * 400 + "1"]),
)


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


# ---------------------------------------------------------------- point files
def point_table(columns):
    cell_counts = st.sampled_from([columns] * 6 + [columns - 1, columns + 1, 0])
    row = cell_counts.flatmap(lambda n: st.lists(number_token, min_size=n, max_size=n))
    line = st.builds(lambda cells, sep, comment: sep.join(cells) + comment, row,
                     st.sampled_from([" ", ",", "\t", ", ", "  "]),
                     st.sampled_from(["", "", " # Maß", "# only a comment", "\t"]))
    return st.builds(lambda bom, lines, nl: bom + nl.join(lines) + nl, st.sampled_from(["", "", "\ufeff"]),
                     st.lists(line, max_size=6), NEWLINES)


@pytest.mark.parametrize("columns", [2, 3])
@FUZZ
@given(data=st.one_of(st.binary(max_size=300), encoded(odd_text), encoded(point_table(2)), encoded(point_table(3))))
@example(data=b"1 2 3\r\n4 5 6\r\n")
@example(data="\ufeff1 2 3\n".encode())
def test_read_points_file_fuzz(fuzz_dir, columns, data):
    f = fuzz_dir / f"points{columns}.txt"
    f.write_bytes(data)
    pts = outcome(lambda: read_points_file(f, columns), f)
    if pts is not None:
        assert pts.ndim == 2 and pts.shape[1] == columns and len(pts) >= 1 and pts.dtype == np.float64
        assert np.all(np.isfinite(pts)) and np.all(np.abs(pts) <= MAX_MAGNITUDE)


# ---------------------------------------------------------------- calibrations
def rotation(a, b, c):
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    Rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


angle = st.floats(-math.pi, math.pi)
focal = st.floats(50, 1e5)
coord = st.floats(-100, 100)


@st.composite
def camera_KRt(draw):
    K = np.array([[draw(focal), draw(st.floats(-5, 5)), draw(coord)], [0, draw(focal), draw(coord)], [0, 0, 1.0]])
    R = rotation(draw(angle), draw(angle), draw(angle))
    t = np.array([draw(coord), draw(coord), draw(coord)])
    return K, R, t


valid_P = camera_KRt().map(lambda krt: (krt[0] @ np.hstack([krt[1], krt[2][:, None]])).tolist())
json_number = st.one_of(st.floats(width=64), st.integers(-10**30, 10**30), st.sampled_from([0, 0.0, 1e-300, 1e300]))
json_leaf = st.one_of(st.none(), st.booleans(), json_number, st.text(max_size=4))
json_junk = st.recursive(json_leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                            st.dictionaries(st.text(max_size=3), inner, max_size=3)),
                         max_leaves=12)
P_value = st.one_of(
    valid_P,
    valid_P.map(lambda P: [P[0], P[1], [0.0, 0.0, 0.0, P[2][3]]]),                      # singular
    st.lists(st.lists(json_number, min_size=4, max_size=4), min_size=3, max_size=3),  # right shape
    st.lists(st.lists(json_leaf, min_size=3, max_size=5), min_size=2, max_size=4),    # ragged, mixed types
    json_junk,
)
camera_entry = st.one_of(st.fixed_dictionaries({"P": P_value}), st.fixed_dictionaries({"P": valid_P}), json_junk)
calib_doc = st.one_of(st.fixed_dictionaries({"cameras": st.lists(camera_entry, min_size=0, max_size=3)}),
                      st.fixed_dictionaries({"cameras": st.lists(st.fixed_dictionaries({"P": valid_P}), min_size=2,
                                                                 max_size=3)}),
                      json_junk)
calib_json_text = st.builds(lambda doc, indent, pre: pre + json.dumps(doc, indent=indent, allow_nan=True),
                            calib_doc, st.sampled_from([None, 2]), st.sampled_from(["", " \n", "\ufeff"]))


def fmt(x):
    return repr(float(x))


@st.composite
def par_text(draw):
    """A valid par file of images a.png, b.png (and maybe c.png)."""
    names = draw(st.sampled_from([["a.png", "b.png"], ["a.png", "b.png", "c.png"], ["b.png", "a.png"]]))
    lines = []
    for n in names:
        K, R, t = draw(camera_KRt())
        lines.append(" ".join([n] + [fmt(v) for v in (*K.ravel(), *R.ravel(), *t)]))
    head = draw(st.sampled_from([[str(len(names))], [str(len(names))], [], [str(len(names) + 1)]]))
    return draw(NEWLINES).join(head + lines) + "\n"


par_random = st.builds(
    lambda count, lines, nl: nl.join(count + lines),
    st.sampled_from([[], ["2"], ["x"], ["-1"], ["2.0"], ["99999999999"]]),
    st.lists(st.builds(lambda n, v: " ".join([n] + v), st.sampled_from(["a.png", "b.png", "é.png", "#"]),
                       st.lists(number_token, min_size=19, max_size=23)), max_size=3),
    NEWLINES)
par_content = st.one_of(mutated(par_text(), number_token), par_random)
NAMES = st.sampled_from([None, ["a.png"], ["a.png", "b.png"], ["b.png", "c.png", "a.png"], ["z.png", "a.png"]])


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), encoded(odd_text),
                      encoded(st.one_of(calib_json_text, mutated(calib_json_text, number_token),
                                        par_content))),
       suffix=st.sampled_from([".json", ".txt", "_par.txt", ""]), names=NAMES)
@example(data=b'{"cameras": [{"P": [[0,0,0,0],[0,0,0,0],[0,0,0,0]]}, {"P": [[0,0,0,0],[0,0,0,0],[0,0,0,0]]}]}',
         suffix=".json", names=None)
@example(data=b"[" * 50000 + b"]" * 50000, suffix=".json", names=None)
def test_read_calibration_fuzz(fuzz_dir, data, suffix, names):
    f = fuzz_dir / f"calib{suffix}"
    f.write_bytes(data)
    cams = outcome(lambda: read_calibration(f, names), f)
    if cams is not None:
        assert isinstance(cams, list) and len(cams) == 2
        for P in cams:
            assert_camera(P)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), encoded(odd_text), encoded(par_content)))
def test_read_middlebury_par_fuzz(fuzz_dir, data):
    f = fuzz_dir / "fuzz_par.txt"
    f.write_bytes(data)
    cams = outcome(lambda: read_middlebury_par(f), f)
    if cams is not None:
        assert isinstance(cams, dict) and cams
        for name, P in cams.items():
            assert isinstance(name, str) and name
            assert_camera(P)


# ---------------------------------------------------------------- image lists
IMAGE_NAMES = ["a.png", "b.jpg", "café.png", "日本.png", "sub/c.ppm", "with space.png"]


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("images")
    (d / "sub").mkdir()
    (d / "folder.png").mkdir()  # a folder with an image's name
    img = np.zeros((4, 5, 3), np.uint8)
    for n in IMAGE_NAMES:
        assert cv2.imencode(".png", img)[0]
        (d / n).write_bytes(cv2.imencode("." + n.rsplit(".", 1)[1], img)[1].tobytes())
    return d


list_line = st.one_of(
    st.sampled_from(IMAGE_NAMES), st.sampled_from(IMAGE_NAMES).map(lambda n: f"  {n}\t"),
    st.sampled_from(["", "# comment é", "missing.png", "folder.png", "sub", "..", "/", "\x00a.png", "a.png\x85"]),
    st.text(st.one_of(st.characters(), st.sampled_from(ODD_CHARS)), max_size=12),
)
list_text = st.builds(lambda bom, lines, nl: bom + nl.join(lines), st.sampled_from(["", "", "\ufeff"]),
                      st.lists(list_line, max_size=6), NEWLINES)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), encoded(odd_text), encoded(list_text), encoded(list_text)),
       name=st.sampled_from(["list.txt", "list.txt", "list", "list.lst", "list.png", "list.mp4"]))
def test_list_images_fuzz(image_dir, data, name):
    f = image_dir / name
    f.write_bytes(data)
    paths = outcome(lambda: list_images(f), f)
    if paths is not None:
        assert paths and all(p.is_file() for p in paths)


# ---------------------------------------------------------------- images
def _encoded_images():
    img = (np.random.default_rng(3).random((24, 32, 3)) * 255).astype(np.uint8)
    return [cv2.imencode(ext, img)[1].tobytes() for ext in (".png", ".jpg", ".ppm", ".bmp", ".tif", ".webp")]


ENCODED = _encoded_images()


def damage(data, cut, flips, prefix):
    b = bytearray(data[:cut] if cut is not None else data)
    for pos, val in flips:
        if b:
            b[pos % len(b)] = val
    return prefix + bytes(b)


damaged_image = st.builds(damage, st.sampled_from(ENCODED), st.one_of(st.none(), st.integers(0, 3000)),
                          st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=3),
                          st.sampled_from([b"", b"", b"\0", b"GIF89a"]))


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), damaged_image, st.sampled_from(ENCODED)),
       suffix=st.sampled_from([".png", ".jpg", ".ppm", ".tif"]))
def test_read_image_fuzz(fuzz_dir, capfd, data, suffix):
    f = fuzz_dir / f"image{suffix}"
    f.write_bytes(data)
    capfd.readouterr()
    image = outcome(lambda: read_image(f), f)
    if image is not None:
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3 and image.size > 0
    assert capfd.readouterr().err == ""  # libpng, libjpeg and OpenCV kept off the terminal
