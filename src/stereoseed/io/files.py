"""Everything that touches the disk: images, point files, calibrations, JSON, PLY.

Writers are atomic (:mod:`stereoseed.io.atomic`: write to a temporary file in the same folder,
then rename), so an interrupted run never leaves a half-written result. Readers raise :class:`StereoseedError` with
a message naming the file and what to do.
"""
from __future__ import annotations

import codecs
import json
import math
import os
import re
import unicodedata
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import atomic_path, write_json, write_text  # re-exported: the writers' home
from stereoseed.io.decoders import decode_image, one_line
from stereoseed.io.image_header import refuse_huge_image

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")

__all__ = ["read_image", "list_images", "check_image_name", "name_trouble", "read_points_file",
           "read_calibration", "read_calibration_unit", "write_json", "write_text", "atomic_path", "IMAGE_EXTENSIONS",
           "VIDEO_EXTENSIONS"]


# ---------------------------------------------------------------- reading text safely
# Every reader below gives a valid result or a StereoseedError whose message is one line that
# starts with the user's path, says what is wrong and what to do; never another exception.

_CALIB_FORMATS = 'a calib.json ({"cameras": [{"P": 3x4}, {"P": 3x4}]}), a Middlebury *_par.txt or a COLMAP model folder'
_PAR_FORMAT = "give a count line, then one line per image: name, K (9 numbers, row by row), R (9), t (3)"
_LIST_HINT = "give a folder of images or a text file listing them, one path a line"
# extensions of files that are images (to refuse as a list of images or a table), and of videos
_IMAGE_LIKE = IMAGE_EXTENSIONS + (".gif", ".jp2", ".j2k", ".exr", ".hdr", ".pic", ".pnm", ".pam", ".pfm",
                                  ".heic", ".heif", ".avif", ".jxl", ".dng", ".raw", ".cr2", ".nef", ".arw")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv")
_BINARY_BYTES = re.compile(rb"[\x00-\x08\x0e-\x1a\x1c-\x1f]")  # control bytes no text file holds
_BINARY_CHARS = re.compile(r"[\x00-\x08\x0e-\x1a\x1c-\x1f]")
_NEWLINE = re.compile(r"\r\n|\r|\n")  # only these end a line (not \x85, \u2028..., which names may hold)
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)  # no '_', no non-ASCII digits
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.ASCII | re.IGNORECASE)
# numbers whose magnitude is beyond this are refused: no coordinate or camera entry is that large,
# and products of three of them stay finite in float64 (so no overflow later)
MAX_MAGNITUDE = 1e100
# a left 3x3 block of P whose smallest singular value is below this fraction of its largest is
# singular (condition number above 1e10; a real camera with f = 1e6 px is at 1e-6)
SINGULAR_RATIO = 1e-10


def _image_format(data: bytes) -> str | None:
    """The image format ``data`` starts with (by its signature), or None."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if data.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if data.startswith((b"GIF87a", b"GIF89a")):
        return "GIF"
    if data.startswith((b"II*\x00", b"MM\x00*")):
        return "TIFF"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    if data.startswith(b"BM") and _BINARY_BYTES.search(data[:54]):
        return "BMP"
    # binary PNM (P4-P6) with any whitespace; text PNM (P1-P3) only with the magic alone on its
    # line, so that a par or list line "P1 800 0 ..." is not taken for an image
    if re.match(rb"(?:P[4-6]\s+|P[1-3][ \t]*\r?\n\s*)(?:#[^\n]*\n\s*)*\d+\s+\d+\s", data):
        return "PNM"
    return None


def _read_bytes(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise StereoseedError(f"{path}: cannot read the {what} ({one_line(e.strerror or e.__class__.__name__)}); "
                              "check that it is a readable file") from None


def _read_text(path: Path, what: str, hint: str, latin1: bool = False) -> str:
    """The text of the file ``path`` (a ``what``): UTF-8 with or without a BOM, UTF-16 with a BOM
    and, with ``latin1``, any other bytes as Latin-1. Refuses an image, binary content and (without
    ``latin1``) bytes that are not UTF-8, with a message ending in ``hint``."""
    data = _read_bytes(path, what)
    kind = _image_format(data)
    if kind:
        raise StereoseedError(f"{path}: is a {kind} image, not a {what}; {hint}")
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            text = data.decode("utf-16")
        except UnicodeDecodeError:
            raise StereoseedError(f"{path}: broken UTF-16 text; save the {what} as UTF-8") from None
        if _BINARY_CHARS.search(text):
            raise StereoseedError(f"{path}: binary content, not a {what}; {hint}")
        return text
    if _BINARY_BYTES.search(data):
        raise StereoseedError(f"{path}: binary content, not a {what}; {hint}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        if latin1:
            return data.decode("latin-1")
        raise StereoseedError(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); save the "
                              f"{what} as UTF-8 text; {hint}") from None


def _numbers(fields: list[str], where: str) -> list[float]:
    """``fields`` as finite numbers of magnitude <= MAX_MAGNITUDE; a message at ``where`` otherwise."""
    values = []
    for f in fields:
        if not _NUMBER.fullmatch(f):
            if _NON_FINITE.fullmatch(f):
                raise StereoseedError(f"{where}: NaN or infinite value {one_line(f)}; fix or remove the line")
            raise StereoseedError(f"{where}: not a number: {one_line(f, 40)}; fix or remove the line")
        v = float(f)
        if not abs(v) <= MAX_MAGNITUDE:
            raise StereoseedError(f"{where}: {one_line(f, 40)} is out of range (magnitude above {MAX_MAGNITUDE:g}); "
                                  "fix or remove the line")
        values.append(v)
    return values


def _missing_message(path: Path, what: str) -> str:
    if path.is_dir():
        return f"{path}: is a folder, not a {what}; give the file"
    return f"{path}: {what} not found; check the path"


# ---------------------------------------------------------------- images
def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as uint8 BGR (H, W, 3); clear error if missing, unreadable or empty.

    The bytes are read by Python and decoded by ``cv2.imdecode`` (so non-ASCII paths work on
    every platform); what libpng, libjpeg or OpenCV print while decoding is kept off the terminal
    and quoted in the message when the image cannot be decoded. A truncated or damaged file is
    refused (``cv2.imdecode`` refuses a truncated JPEG which ``cv2.imread`` pads with grey). A
    black or flat image is an image: not refused here."""
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: is a folder, not an image; give an image file" if path.is_dir()
                              else f"{path}: image not found; check the path")
    refuse_huge_image(path)  # by its header, before its bytes are read and decoded
    data = _read_bytes(path, "image")
    if not data:
        raise StereoseedError(f"{path}: empty file (0 bytes), not an image; give a PNG, JPEG, PPM, BMP, TIFF or WebP image")
    image, detail = decode_image(data)
    if image is None:
        kind = _image_format(data)
        what = (f"a damaged or truncated {kind} file" if kind else "not an image format it reads")
        raise StereoseedError(f"{path}: not a readable image (OpenCV cannot decode it: {what}"
                              + (f": {detail}" if detail else "")
                              + "); give an intact PNG, JPEG, PPM, BMP, TIFF or WebP image")
    return image


def name_trouble(name: str) -> str | None:
    """What in an image's file name no export format (COLMAP, NVM, Bundler: a name a line, or
    UTF-8 text) can hold, else None."""
    for c in name:
        kind = unicodedata.category(c)
        if kind in ("Zl", "Zp") or c in "\n\r\x0b\x0c\x1c\x1d\x1e\x85":
            return "a line break"
        if kind == "Cc":
            return f"a control character ({repr(c)[1:-1]})"
        if kind == "Cs":
            return "bytes that are not UTF-8"
    return None


def check_image_name(path: str | os.PathLike, where: str | os.PathLike) -> None:
    """Refuse an image (or video) whose file name no result file can hold, with a message at
    ``where``."""
    trouble = name_trouble(Path(path).name)
    if trouble:
        raise StereoseedError(f"{where}: the image name '{one_line(Path(path).name)}' holds {trouble}, which the "
                              "results cannot hold (cameras.json, COLMAP, NVM, Bundler); rename the file")


def list_images(source: str | os.PathLike) -> list[Path]:
    """Image paths in order: a folder (its images, by extension, in name order) or a text file
    (one path a line, relative paths resolved against the file's folder; blank lines and '#'
    comments skipped; leading and trailing spaces stripped).

    A list file is read as UTF-8 (a BOM tolerated) or UTF-16 with a BOM (PowerShell's ``>``);
    any other bytes are read as Latin-1 (a Windows "ANSI" list of accented names), after which
    each listed image must exist. Lines end at \\n, \\r\\n or \\r only. Refused with a message: an
    image or a video given instead of a folder or list, a binary file, a list without paths, a
    listed image that does not exist."""
    source = Path(source)
    if source.is_dir():
        try:
            paths = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
        except OSError as e:
            raise StereoseedError(f"{source}: cannot list the folder ({one_line(e.strerror or e.__class__.__name__)}); "
                                  "check its permissions") from None
        if not paths:
            raise StereoseedError(f"{source}: no images in this folder ({', '.join(IMAGE_EXTENSIONS)})")
        for p in paths:
            check_image_name(p, source)
        return paths
    if not source.is_file():
        raise StereoseedError(f"{source}: not found; {_LIST_HINT}")
    suffix = source.suffix.lower()
    if suffix in _IMAGE_LIKE:
        raise StereoseedError(f"{source}: is an image, not a folder of images or a list of them; give the folder "
                              "that holds the sequence, or a text file listing its images one a line")
    if suffix in VIDEO_EXTENSIONS:
        raise StereoseedError(f"{source}: is a video; extract its frames into a folder first (e.g. ffmpeg -i "
                              f"{one_line(source.name)} frames/%04d.png) and give that folder")
    text = _read_text(source, "list of images", _LIST_HINT, latin1=True)
    paths, linenos = [], []
    for lineno, line in enumerate(_NEWLINE.split(text), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        p = Path(line)
        paths.append(p if p.is_absolute() else source.parent / p)
        linenos.append(lineno)
    if not paths:
        raise StereoseedError(f"{source}: the list holds no image paths; {_LIST_HINT}")
    missing = [(p, n) for p, n in zip(paths, linenos) if not p.is_file()]
    if missing:
        p, n = missing[0]
        what = "is a folder, not an image" if p.is_dir() else "not found"
        raise StereoseedError(f"{source}:{n}: listed image {what}: {one_line(str(p), 160)}"
                              + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
                              + "; check the paths (relative ones are read from the list's folder)")
    for p, n in zip(paths, linenos):
        check_image_name(p, f"{source}:{n}")
    return paths


def check_image_output(path: str | os.PathLike) -> Path:
    """Refuse, before any work, an output image path OpenCV cannot encode (by its extension)."""
    path = Path(path)
    if not path.suffix or not cv2.haveImageWriter(str(path)):
        raise StereoseedError(f"{path}: cannot write an image with this extension; give a .png or .jpg path")
    return path


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Encode ``image`` (uint8 grey or BGR) by the path's extension and write it atomically."""
    path = check_image_output(path)
    ok, data = cv2.imencode(path.suffix, image)
    if not ok:
        raise StereoseedError(f"{path}: OpenCV could not encode the image")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())
    return path


# ---------------------------------------------------------------- point files
def read_points_file(path: str | os.PathLike, columns: int) -> np.ndarray:
    """Read a whitespace/comma separated table with ``columns`` numbers a line -> (N, columns).

    Blank lines and '#' comments are skipped. Any other line must hold exactly ``columns``
    finite numbers (plain decimal notation; magnitude at most ``MAX_MAGNITUDE``). The file is
    read as UTF-8 (a BOM tolerated), UTF-16 with a BOM, or else Latin-1 (the numbers are ASCII
    in every case; only comments can hold other characters); lines end at \\n, \\r\\n or \\r.
    """
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(_missing_message(path, "points file"))
    hint = f"give a text file with {columns} numbers a line"
    text = _read_text(path, "text table of points", hint, latin1=True)
    rows = []
    for lineno, line in enumerate(_NEWLINE.split(text), 1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        if len(fields) != columns:
            raise StereoseedError(f"{path}:{lineno}: expected {columns} numbers a line, found {len(fields)}; "
                                  "fix or remove the line")
        rows.append(_numbers(fields, f"{path}:{lineno}"))
    if not rows:
        raise StereoseedError(f"{path}: no points in the file; {hint}")
    return np.array(rows, dtype=np.float64)


# ---------------------------------------------------------------- calibrations
def _describe(obj: Any) -> str:
    """A JSON value's kind, for messages."""
    if isinstance(obj, bool) or obj is None:
        return json.dumps(obj)
    if isinstance(obj, (int, float)):
        return "a number"
    if isinstance(obj, str):
        return "a string"
    if isinstance(obj, dict):
        return "an object"
    if isinstance(obj, list):
        return f"a list of {len(obj)}"
    return type(obj).__name__


def _check_P(P: Any, where: str) -> np.ndarray:
    """P as a (3, 4) float64 array: from an array or a JSON value (3 lists of 4 numbers); finite,
    entries of magnitude in [1/MAX_MAGNITUDE, MAX_MAGNITUDE] and a left 3x3 block that is not
    singular relative to its own scale (smallest singular value over largest >= SINGULAR_RATIO)."""
    if not isinstance(P, np.ndarray):
        if not (isinstance(P, list) and len(P) == 3 and all(isinstance(r, list) and len(r) == 4 for r in P)):
            got = _describe(P)
            if isinstance(P, list) and P and all(isinstance(r, list) for r in P):
                got += " rows of " + "/".join(str(len(r)) for r in P[:5]) + (" ..." if len(P) > 5 else "") + " items"
            raise StereoseedError(f"{where}: 'P' is {got}, not a 3x4 matrix; give 3 rows of 4 numbers "
                                  "([[p11, p12, p13, p14], ...])")
        for row in P:
            for v in row:
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise StereoseedError(f"{where}: 'P' holds {_describe(v)}; give 3 rows of 4 numbers")
                if isinstance(v, int) and abs(v) > MAX_MAGNITUDE:
                    raise StereoseedError(f"{where}: 'P' holds a number out of range; give P in pixels (K [R | t])")
        P = [[float(v) for v in row] for row in P]
    P = np.array(P, dtype=np.float64)
    if P.shape != (3, 4):
        raise StereoseedError(f"{where}: 'P' has shape {P.shape}, not (3, 4); give a 3x4 projection matrix")
    if not np.all(np.isfinite(P)):
        raise StereoseedError(f"{where}: 'P' has NaN or infinite entries; give a finite 3x4 projection matrix")
    scale = float(np.abs(P).max())
    if scale == 0:
        raise StereoseedError(f"{where}: 'P' is all zeros; give the camera's 3x4 projection matrix K [R | t]")
    if not 1 / MAX_MAGNITUDE <= scale <= MAX_MAGNITUDE:
        raise StereoseedError(f"{where}: 'P' has entries of magnitude {scale:.3g}, out of range; give P in pixels "
                              "(K [R | t]) or rescale it (P is defined up to scale)")
    s = _singular_values(P[:, :3])
    if _singular(s):
        raise StereoseedError(f"{where}: 'P' is not a camera: its left 3x3 block is singular (condition number "
                              f"{(s[0] / s[2]) if s[2] > 0 else float('inf'):.3g}); give P = K [R | t] with K and R "
                              "invertible")
    return P


def _singular_values(M: np.ndarray) -> np.ndarray:
    """Singular values (3,) of a 3x3 matrix scaled to its largest entry (zeros for a zero or
    unusable matrix)."""
    m = float(np.abs(M).max())
    try:
        return np.linalg.svd(M / m, compute_uv=False) if m > 0 else np.zeros(3)
    except np.linalg.LinAlgError:
        return np.zeros(3)


def _singular(s: np.ndarray) -> bool:
    """Whether singular values ``s`` (largest first) are those of a (near) singular matrix."""
    return not s[2] >= SINGULAR_RATIO * s[0] or s[0] == 0


def read_middlebury_par(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Middlebury ``*_par.txt``: first line a count, then "name k11..k33 r11..r33 t1 t2 t3"
    per image, P = K [R | t]. Returns {image name: P (3, 4)}.

    UTF-8 text (a BOM tolerated). Refused with a message naming the line: a count that is not a
    whole number or disagrees with the number of camera lines, a line without a name and 21
    numbers, non-finite numbers, a singular K, an R that is not a rotation (R R^T farther than
    0.01 from I: the fields are out of order), a name given twice."""
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(_missing_message(path, "par file"))
    return _parse_par(_read_text(path, "Middlebury par file", _PAR_FORMAT), path)


def _first_fields(text: str) -> list[str]:
    return next((ln.split() for ln in _NEWLINE.split(text) if ln.strip()), [])


def _parse_par(text: str, path: Path) -> dict[str, np.ndarray]:
    cameras: dict[str, np.ndarray] = {}
    line_of: dict[str, int] = {}
    count = None
    for lineno, line in enumerate(_NEWLINE.split(text), 1):
        fields = line.split()
        if not fields:
            continue
        where = f"{path}:{lineno}"
        if len(fields) == 1 and count is None and not cameras:
            if not re.fullmatch(r"\d{1,9}", fields[0], re.ASCII):
                raise StereoseedError(f"{where}: the count line must be a whole number, found {one_line(fields[0], 40)}; "
                                      f"{_PAR_FORMAT}")
            count = int(fields[0])
            continue
        if len(fields) != 22:
            raise StereoseedError(f"{where}: a par line holds a name and 21 numbers, found {len(fields)} fields; "
                                  f"{_PAR_FORMAT}")
        name = fields[0]
        if name in cameras:
            raise StereoseedError(f"{where}: image '{one_line(name)}' is given twice (first on line {line_of[name]}); "
                                  "keep one line per image")
        v = np.array(_numbers(fields[1:], where))
        K, R, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21]
        if _singular(_singular_values(K)):
            raise StereoseedError(f"{where}: K of {one_line(name)} is singular; check the 9 numbers after the name "
                                  "(K row by row: fx s cx 0 fy cy 0 0 1)")
        off = float(np.abs(R @ R.T - np.eye(3)).max())
        if not off <= 1e-2:
            raise StereoseedError(f"{where}: R of {one_line(name)} is not a rotation (R R^T differs from I by "
                                  f"{off:.2g}); check numbers 10 to 18 (R row by row) and the field order")
        cameras[name] = _check_P(K @ np.hstack([R, t[:, None]]), f"{where}: {one_line(name)}")
        line_of[name] = lineno
    if not cameras:
        raise StereoseedError(f"{path}: no cameras in the par file; {_PAR_FORMAT}")
    if count is not None and count != len(cameras):
        raise StereoseedError(f"{path}: the count line says {count} cameras but {len(cameras)} follow; fix the count "
                              "or restore the missing lines")
    return cameras


def read_calibration(path: str | os.PathLike, image_names: Iterable[str] | None = None) -> list[np.ndarray]:
    """The stereo pair's projection matrices [P1, P2] from a calib.json, a Middlebury par file
    or a COLMAP model folder.

    The format is told by the content, not the name: a folder is a COLMAP model (cameras +
    images, .txt or .bin); a file whose first non-space character is '{' or '[' is JSON, any
    other text a par file. calib.json: ``{"cameras": [{"P": 3x4}, {"P": 3x4}, ...]}`` (only
    "P" is required; the first two cameras are the pair). Middlebury ``*_par.txt`` and COLMAP
    models: cameras are looked up by the names of the first two images. Text is UTF-8 (a BOM
    tolerated) or UTF-16 with a BOM; anything else is refused with a message.
    """
    path = Path(path)
    names = list(image_names or [])
    if path.is_dir():
        from stereoseed.io.colmap import read_colmap_cameras

        try:
            cams = read_colmap_cameras(path)
        except (ValueError, ArithmeticError, IndexError, KeyError, TypeError) as e:
            raise StereoseedError(f"{path}: the COLMAP model cannot be read ({e.__class__.__name__}: "
                                  f"{one_line(str(e), 80)}); export it again (colmap model_converter)") from None
        return _pair_by_name(cams, names, path, "COLMAP model")
    if not path.is_file():
        raise StereoseedError(f"{path}: calibration file not found; give {_CALIB_FORMATS}")
    text = _read_text(path, "calibration", f"give {_CALIB_FORMATS}")
    start = text.lstrip()[:1]
    if not start:
        raise StereoseedError(f"{path}: empty file; give {_CALIB_FORMATS}")
    if start in "{[":
        return _calibration_json(text, path)
    first = _first_fields(text)
    if not (len(first) == 22 or len(first) == 1 and re.fullmatch(r"\d+", first[0], re.ASCII)):
        raise StereoseedError(f"{path}: not a calibration stereoseed reads (neither JSON nor a Middlebury par file); "
                              f"give {_CALIB_FORMATS}")
    return _pair_by_name(_parse_par(text, path), names, path, "par file")


def read_calibration_unit(path: str | os.PathLike, given: str | None = None) -> str | None:
    """The unit of the calibration's coordinates (the model is metric in it): calib.json's "unit"
    (such as "mm"), else ``given`` (``reconstruct --unit``: a par file or a COLMAP model names
    none), else None; the rest of the file is :func:`read_calibration`'s to judge."""
    path = Path(path)
    text = _read_text(path, "calibration", f"give {_CALIB_FORMATS}") if path.is_file() else ""
    try:
        data = json.loads(text) if text.lstrip()[:1] == "{" else None
    except (ValueError, RecursionError):
        data = None
    named = data.get("unit") if isinstance(data, dict) else None
    for what, unit in ((f'{path}: "unit"', named), ("--unit", given)):
        if unit is not None and not (isinstance(unit, str) and 0 < len(unit.strip()) <= 20):
            raise StereoseedError(f'{what} is {one_line(json.dumps(unit), 40)}; give a short name such as "mm", or leave it out')
    named, given = (None if u is None else u.strip() for u in (named, given))
    if named and given and given != named:
        raise StereoseedError(f'{path} names its unit "{named}", not "{given}": leave --unit out')
    return named or given


_CALIB_JSON = '{"cameras": [{"P": 3x4}, {"P": 3x4}]}'


def _calibration_json(text: str, path: Path) -> list[np.ndarray]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise StereoseedError(f"{path}:{e.lineno}:{e.colno}: not valid JSON ({one_line(e.msg, 60)}); "
                              f"give {_CALIB_JSON}") from None
    except (ValueError, RecursionError) as e:  # an integer of > 4300 digits, nesting too deep
        raise StereoseedError(f"{path}: not a JSON stereoseed reads ({e.__class__.__name__}); "
                              f"give {_CALIB_JSON}") from None
    if not isinstance(data, dict):
        raise StereoseedError(f"{path}: the JSON is {_describe(data)}, not an object; give {_CALIB_JSON}")
    cams = data.get("cameras")
    if not isinstance(cams, list):
        raise StereoseedError(f'{path}: no "cameras" list' + (f" (it is {_describe(cams)})" if "cameras" in data else "")
                              + f"; give {_CALIB_JSON}")
    if len(cams) < 2:
        raise StereoseedError(f'{path}: "cameras" holds {len(cams)} camera(s); give both cameras of the pair: '
                              f"{_CALIB_JSON}")
    out = []
    for i, cam in enumerate(cams[:2]):
        if not isinstance(cam, dict) or "P" not in cam:
            raise StereoseedError(f"{path}: camera {i} has no 'P'" + (f" (it is {_describe(cam)})"
                                                                      if not isinstance(cam, dict) else "")
                                  + '; give each camera {"P": 3x4 projection matrix}')
        out.append(_check_P(cam["P"], f"{path}: camera {i}"))
        _check_lens(cam, out[-1], f"{path}: camera {i}")
    return out


def _check_lens(cam: dict, P: np.ndarray, where: str) -> None:
    """Refuse a camera's "distortion" that no lens can have over its image (it folds the image
    back or moves its corners by more than their radius: a typo such as k1 = 50). The form of
    the entry (4 or 5 finite numbers) is checked where the lens is read
    (:func:`stereoseed.calibration.lens_calibration.read_lenses`)."""
    from stereoseed.geometry.camera import Camera
    from stereoseed.geometry.lens import lens_problem

    d = cam.get("distortion")
    if not (isinstance(d, list) and len(d) in (4, 5) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             and math.isfinite(v) for v in d)):
        return
    K = Camera(P).K
    if isinstance(cam.get("K"), list):
        try:
            K = np.array(cam["K"], np.float64).reshape(3, 3)
        except (ValueError, TypeError):
            pass
    size = cam.get("image_size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        size = (2.0 * K[0, 2] + 1.0, 2.0 * K[1, 2] + 1.0)  # the principal point taken at the centre
    problem = lens_problem(d, K, size) if np.all(np.isfinite(K)) and K[0, 0] and K[1, 1] else None
    if problem:
        raise StereoseedError(f"{where}: 'distortion' {problem}; check the coefficients (OpenCV's order: k1 k2 p1 p2 "
                              "[k3])")


def _pair_by_name(cams: dict[str, np.ndarray], names: list[str], path: Path, what: str) -> list[np.ndarray]:
    if len(names) < 2:
        raise StereoseedError(f"{path}: a {what} needs the image names to look the pair up; give the images too")
    missing = [n for n in names[:2] if n not in cams]
    if missing:
        raise StereoseedError(f"{path}: no camera for image '{one_line(missing[0])}' in the {what}; the first two "
                              f"images must be the calibrated pair, named as in the {what}")
    return [_check_P(cams[n], f"{path}: {one_line(n)}") for n in names[:2]]
