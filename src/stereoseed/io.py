"""Everything that touches the disk: images, point files, calibrations, JSON, PLY.

Writers are atomic (write to a temporary file in the same folder, then rename), so an
interrupted run never leaves a half-written result. Readers raise :class:`StereoseedError` with
a message naming the file and what to do.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from .errors import StereoseedError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")

__all__ = ["read_image", "list_images", "read_points_file", "read_calibration", "write_json",
           "write_text", "write_ply", "read_ply", "read_ply_vertices", "atomic_path", "IMAGE_EXTENSIONS"]


# ---------------------------------------------------------------- atomic writing
def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()  # what open() would give: mkstemp's files are 0600


class atomic_path:
    """Context manager yielding a temporary path that replaces ``path`` on success (created with
    the user's umask); on failure the temporary file is removed. Errors name ``path``, never the
    temporary file."""

    def __init__(self, path: str | os.PathLike, suffix: str = ""):
        self.path = Path(path)
        self.suffix = suffix or self.path.suffix

    def __enter__(self) -> Path:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix="." + self.path.name + ".", suffix=".tmp" + self.suffix,
                                       dir=self.path.parent)
        except OSError as e:
            raise StereoseedError(f"{self.path}: cannot write ({e.strerror or e})") from None
        os.close(fd)
        self.tmp = Path(tmp)
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                os.chmod(self.tmp, _FILE_MODE)
                os.replace(self.tmp, self.path)
                return False
            except OSError as e:
                self.tmp.unlink(missing_ok=True)
                raise StereoseedError(f"{self.path}: cannot write ({e.strerror or e})") from None
        self.tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise StereoseedError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        return False


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically; NumPy arrays become lists."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_jsonable) + "\n")
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


# ---------------------------------------------------------------- images
def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as uint8 BGR (H, W, 3); clear error if missing, unreadable or empty."""
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: image not found; check the path")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise StereoseedError(f"{path}: not a readable image (OpenCV cannot decode it); give a PNG, JPEG, PPM...")
    return image


def list_images(source: str | os.PathLike) -> list[Path]:
    """Image paths in order: a folder (images in name order) or a text file (one path a line,
    relative paths resolved against the file's folder; blank lines and '#' comments skipped)."""
    source = Path(source)
    if source.is_dir():
        paths = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
        if not paths:
            raise StereoseedError(f"{source}: no images in this folder ({', '.join(IMAGE_EXTENSIONS)})")
        return paths
    if not source.is_file():
        raise StereoseedError(f"{source}: not found; give a folder of images or a text file listing them")
    paths = []
    for line in source.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        p = Path(line)
        paths.append(p if p.is_absolute() else source.parent / p)
    if not paths:
        raise StereoseedError(f"{source}: the list holds no image paths")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise StereoseedError(f"{source}: listed image not found: {missing[0]}"
                              + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
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
    finite numbers.
    """
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: file not found")
    rows = []
    try:
        text = path.read_text()
    except (UnicodeDecodeError, OSError) as e:
        raise StereoseedError(f"{path}: cannot read as text ({e.__class__.__name__})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != columns:
            raise StereoseedError(f"{path}:{lineno}: expected {columns} numbers a line, found {len(fields)}")
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise StereoseedError(f"{path}:{lineno}: not a number in {line!r}") from None
        if not all(np.isfinite(values)):
            raise StereoseedError(f"{path}:{lineno}: NaN or infinite value; fix or remove the line")
        rows.append(values)
    if not rows:
        raise StereoseedError(f"{path}: no points in the file")
    return np.array(rows, dtype=np.float64)


# ---------------------------------------------------------------- calibrations
def _check_P(P: Any, where: str) -> np.ndarray:
    try:
        P = np.asarray(P, dtype=np.float64)
    except (TypeError, ValueError):
        raise StereoseedError(f"{where}: 'P' must be a 3x4 matrix of numbers") from None
    if P.shape != (3, 4):
        raise StereoseedError(f"{where}: 'P' must be a 3x4 matrix, got shape {P.shape}")
    if not np.all(np.isfinite(P)) or abs(np.linalg.det(P[:, :3])) < 1e-12 * np.abs(P).max() ** 3:
        raise StereoseedError(f"{where}: 'P' is not a finite camera (NaN or singular left 3x3 block)")
    return P


def read_middlebury_par(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Middlebury ``*_par.txt``: first line a count, then "name k11..k33 r11..r33 t1 t2 t3"
    per image, P = K [R | t]. Returns {image name: P (3, 4)}."""
    path = Path(path)
    cameras: dict[str, np.ndarray] = {}
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    for lineno, fields in enumerate(lines, 1):
        if len(fields) == 1 and lineno == 1:
            continue  # the count line
        if len(fields) != 22:
            raise StereoseedError(f"{path}:{lineno}: a par line holds a name and 21 numbers, found {len(fields)} fields")
        try:
            v = np.array([float(f) for f in fields[1:]])
        except ValueError:
            raise StereoseedError(f"{path}:{lineno}: not a number in the camera parameters") from None
        K, R, t = v[:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21]
        cameras[fields[0]] = _check_P(K @ np.hstack([R, t[:, None]]), f"{path}:{lineno}")
    if not cameras:
        raise StereoseedError(f"{path}: no cameras in the par file")
    return cameras


def read_calibration(path: str | os.PathLike, image_names: Iterable[str] | None = None) -> list[np.ndarray]:
    """The stereo pair's projection matrices [P1, P2] from a calib.json, a Middlebury par file
    or a COLMAP model folder.

    calib.json: ``{"cameras": [{"P": 3x4, ...}, {"P": 3x4, ...}]}`` (only "P" is required).
    Middlebury ``*_par.txt`` and COLMAP model folders (cameras + images, .txt or .bin): cameras
    are looked up by the names of the first two images.
    """
    path = Path(path)
    names = list(image_names or [])
    if path.is_dir():
        from .export import read_colmap_cameras

        return _pair_by_name(read_colmap_cameras(path), names, path, "COLMAP model")
    if not path.is_file():
        raise StereoseedError(f"{path}: calibration file not found")
    if path.suffix.lower() == ".txt":
        return _pair_by_name(read_middlebury_par(path), names, path, "par file")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise StereoseedError(f"{path}: not valid JSON ({e.__class__.__name__}); expected "
                              '{"cameras": [{"P": ...}, {"P": ...}]}') from None
    cams = data.get("cameras") if isinstance(data, dict) else None
    if not isinstance(cams, list) or len(cams) < 2:
        raise StereoseedError(f'{path}: expected {{"cameras": [{{"P": 3x4}}, {{"P": 3x4}}]}} with two cameras')
    out = []
    for i, cam in enumerate(cams[:2]):
        if not isinstance(cam, dict) or "P" not in cam:
            raise StereoseedError(f"{path}: camera {i} has no 'P'")
        out.append(_check_P(cam["P"], f"{path}: camera {i}"))
    return out


def _pair_by_name(cams: dict[str, np.ndarray], names: list[str], path: Path, what: str) -> list[np.ndarray]:
    if len(names) < 2:
        raise StereoseedError(f"{path}: a {what} needs the image names to look the pair up")
    missing = [n for n in names[:2] if n not in cams]
    if missing:
        raise StereoseedError(f"{path}: no camera for image {missing[0]!r} in the {what}")
    return [_check_P(cams[n], f"{path}: {n}") for n in names[:2]]


# ---------------------------------------------------------------- PLY
_PLY_TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u4": "uint", "i2": "short",
              "u2": "ushort", "i1": "char"}


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None,
              properties: dict[str, np.ndarray] | None = None, faces: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY, atomically: x y z (float32), red green blue (uint8), then each
    extra per-vertex property of ``properties`` (name -> (N,) array; float32, int32 or uint8 by
    its dtype; "nx", "ny", "nz" for normals), and triangles ``faces`` (F, 3) as a face element.

    points: (N, 3); colors: (N, 3) uint8 RGB or None (grey)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if colors is None:
        colors = np.full((len(points), 3), 200, dtype=np.uint8)
    columns = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    extra = {}
    for name, values in (properties or {}).items():
        values = np.asarray(values).reshape(-1)
        kind = "<f4" if values.dtype.kind == "f" else "u1" if values.dtype == np.uint8 else "<i4"
        columns.append((name, kind))
        extra[name] = values.astype(kind)
    vertex = np.empty(len(points), dtype=columns)
    vertex["x"], vertex["y"], vertex["z"] = points.T.astype(np.float32)
    colors = np.asarray(colors).reshape(-1, 3).astype(np.uint8)
    vertex["red"], vertex["green"], vertex["blue"] = colors.T
    for name, values in extra.items():
        vertex[name] = values
    header = ["ply", "format binary_little_endian 1.0", "comment written by stereoseed",
              f"element vertex {len(points)}"]
    header += [f"property {_PLY_TYPES[np.dtype(kind).str.lstrip('<|')]} {name}" for name, kind in columns]
    face_bytes = b""
    if faces is not None:
        faces = np.asarray(faces, np.int32).reshape(-1, 3)
        face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        face["n"], face["v"] = 3, faces
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        face_bytes = face.tobytes()
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(vertex.tobytes())
            fh.write(face_bytes)
    return Path(path)


def read_ply_vertices(path: str | os.PathLike) -> np.ndarray:
    """Every vertex property of any valid PLY (ASCII or binary, via plyfile) as a structured
    array (N,) with one field per property. Raises :class:`StereoseedError` for a file that is
    not a PLY or has no vertex element."""
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: PLY file not found")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"].data
    except (PlyParseError, KeyError, ValueError, UnicodeDecodeError, EOFError) as e:
        raise StereoseedError(f"{path}: not a PLY point cloud with a vertex element ({e})") from None
    return np.asarray(vertex)


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) float64 and colours (N, 3) uint8 (200 grey where the file has none) of any
    PLY (:func:`read_ply_vertices`); refuses a vertex element without x, y, z."""
    vertex = read_ply_vertices(path)
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise StereoseedError(f"{path}: the vertex element has no x, y, z properties ({', '.join(names)})")
    pts = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    if {"red", "green", "blue"} <= set(names):
        cols = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.uint8)
    else:
        cols = np.full((len(pts), 3), 200, np.uint8)
    return pts, cols
