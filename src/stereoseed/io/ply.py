"""PLY point clouds and meshes: written in binary with any per-vertex attributes (atomically),
read back through plyfile, which reads any valid PLY."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.io.files import atomic_path

__all__ = ["write_ply", "read_ply", "read_ply_vertices"]

_PLY_TYPES = {"<f4": "float", "u1": "uchar", "<i4": "int"}  # the property types write_ply writes
GREY = 200  # the colour of points that come without one
_ROWS_PER_WRITE = 1 << 20  # vertices put together and written at once (~50 MB with a dense cloud's properties)


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None,
              properties: dict[str, np.ndarray] | None = None, faces: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY, atomically: x y z (float32), red green blue (uint8), then each
    extra per-vertex property of ``properties`` (name -> (N,) array; float32, int32 or uint8 by
    its dtype; "nx", "ny", "nz" for normals), and triangles ``faces`` (F, 3) as a face element.

    points: (N, 3); colors: (N, 3) uint8 RGB or None (grey)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if colors is None:
        colors = np.full((len(points), 3), GREY, dtype=np.uint8)
    columns = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    extra = {}
    for name, values in (properties or {}).items():
        values = np.asarray(values).reshape(-1)
        kind = "<f4" if values.dtype.kind == "f" else "u1" if values.dtype == np.uint8 else "<i4"
        columns.append((name, kind))
        # one value for every vertex is spread to all of them, as a whole-array assignment would
        extra[name] = np.broadcast_to(values.astype(kind, copy=False), (len(points),))
    header = ["ply", "format binary_little_endian 1.0", "comment written by stereoseed",
              f"element vertex {len(points)}"]
    header += [f"property {_PLY_TYPES[kind]} {name}" for name, kind in columns]
    face_bytes = b""
    if faces is not None:
        faces = np.asarray(faces, np.int32).reshape(-1, 3)
        face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        face["n"], face["v"] = 3, faces
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        face_bytes = face.tobytes()
    header.append("end_header")
    colors = np.broadcast_to(np.asarray(colors).reshape(-1, 3), (len(points), 3))  # (one colour: every vertex's)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            # the rows a chunk at a time: a full-resolution cloud's rows at once would be 400 MB more
            for first in range(0, len(points), _ROWS_PER_WRITE):
                rows = slice(first, first + _ROWS_PER_WRITE)
                vertex = np.empty(len(points[rows]), dtype=columns)
                vertex["x"], vertex["y"], vertex["z"] = points[rows].T.astype(np.float32)
                vertex["red"], vertex["green"], vertex["blue"] = colors[rows].T.astype(np.uint8)
                for name, values in extra.items():
                    vertex[name] = values[rows]
                fh.write(memoryview(vertex).cast("B"))
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
    return _points_and_colours(read_ply_vertices(path), path)


def read_dense_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None,
                                                     np.ndarray | None]:
    """A dense.ply: points and colours as :func:`read_ply`, normals (N, 3) float64, support
    (N,) int64 and confidence (N,) float64, each None where the file has none (a cloud from
    before the multi-view fusion, or another tool's)."""
    vertex = read_ply_vertices(path)
    pts, cols = _points_and_colours(vertex, path)
    names = set(vertex.dtype.names or ())
    normals = (np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=1).astype(np.float64)
               if {"nx", "ny", "nz"} <= names else None)
    support = vertex["support"].astype(np.int64) if "support" in names else None
    confidence = vertex["confidence"].astype(np.float64) if "confidence" in names else None
    return pts, cols, normals, support, confidence


def _points_and_colours(vertex: np.ndarray, path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise StereoseedError(f"{path}: the vertex element has no x, y, z properties ({', '.join(names)})")
    pts = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    if {"red", "green", "blue"} <= set(names):
        cols = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.uint8)
    else:
        cols = np.full((len(pts), 3), GREY, np.uint8)
    return pts, cols
