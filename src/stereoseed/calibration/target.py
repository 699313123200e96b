"""A calibration target (ChArUco boards on the faces of a box, a hand-made cube or one flat
board): its description, ``target.json``, and how it is read.

Printing one is :mod:`stereoseed.calibration.printing` (:func:`make_target`); finding it in a
photo :mod:`stereoseed.calibration.detection` (:func:`detect_target`).

The contract of ``target.json``
-------------------------------
::

    {"unit": "mm", "legacy": false,
     "faces": [{"image": "face_0.png", "size_px": [W, H],
                "origin": [x, y, z], "u_axis": [..], "v_axis": [..],
                "board": {"dictionary": "DICT_5X5_1000", "squares": [nx, ny],
                          "square_px": 350, "marker_px": 252, "first_id": 0,
                          "origin_uv": [u0, v0], "square_mm": .., "marker_mm": ..,
                          "legacy": false}}, ...]}

* The centre of pixel (u, v) of a face image lies at ``origin + u * u_axis + v * v_axis`` in the
  target's frame (mm). Pixel convention: (0, 0) is the centre of the top-left pixel (as OpenCV),
  so the outer edge of the image is at u = -0.5 and u = W - 0.5. A face needs no image: a target
  described from its maker's numbers (``examples/charuco-cube``) may take u and v in mm
  (``u_axis`` a unit vector, ``square_px`` the square in mm).
* The printed side is seen from the side ``-(u_axis x v_axis)`` points to (u to the right, v down
  on the page, u x v points into the page, away from whoever reads it).
* ``board``: the ChArUco board inside the face image. ``origin_uv`` is the (u, v) of the board's
  outer top-left corner, a point between pixels (so half-integer for a generated target: the
  board's first pixel column starts at u = origin_u + 0.5). Chessboard (ChArUco) corner ``k``
  (OpenCV's numbering, row by row from the top-left inner corner, ``nx - 1`` per row) lies at
  ``origin_uv + square_px * (k % (nx - 1) + 1, k // (nx - 1) + 1)``; its 3D point follows from the
  contract above. The markers have ids ``first_id .. first_id + nx * ny // 2 - 1`` in OpenCV's
  order; no two faces share an id. ``legacy`` (per board, or once at the top for every board):
  the board uses OpenCV's layout from before 4.6 (``CharucoBoard.setLegacyPattern``: with an even
  number of rows the top-left square is white); false, the default, is the current layout (the
  top-left square black). ``square_mm`` / ``marker_mm`` are for people; the loader ignores them.
* One face, or faces all on one plane, make a flat target (:attr:`Target.planar`): a camera's
  intrinsics then come from several views of it (Zhang's method), not from one.

A hand-written ``target.json`` for a measured, non-ideal box may give any origin / u_axis /
v_axis per face (faces not square to each other, a printer that scaled by 0.98, ...); where
the faces are not known that well, the calibration estimates where they are
(:mod:`stereoseed.calibration.refine_target`).
"""
from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.io.nesting import read_bounded_text

log = logging.getLogger(__name__)

__all__ = ["load_target", "Target", "Face", "Board", "target_json"]

# smallest / largest spread of the boards' outlines below this: the faces lie on one plane
_COPLANAR_RATIO = 1e-3


# ---------------------------------------------------------------- the target's description
@dataclass(frozen=True)
class Board:
    """A ChArUco board inside a face image, in that image's pixels."""
    dictionary: str
    squares: tuple[int, int]  # (nx, ny) squares across, down
    square_px: float
    marker_px: float
    first_id: int
    origin_uv: tuple[float, float]  # (u, v) of the board's outer top-left corner
    legacy: bool = False  # OpenCV's layout before 4.6 (CharucoBoard.setLegacyPattern)

    @property
    def n_markers(self) -> int:
        return self.squares[0] * self.squares[1] // 2

    @property
    def n_corners(self) -> int:
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        ids = np.arange(self.first_id, self.first_id + self.n_markers, dtype=np.int32)
        board = cv2.aruco.CharucoBoard(self.squares, float(self.square_px), float(self.marker_px), d, ids)
        board.setLegacyPattern(bool(self.legacy))
        return board

    def corner_uv(self, ids: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) face-image (u, v) of the chessboard corners ``ids`` (all of them by default)."""
        ids = np.arange(self.n_corners) if ids is None else np.asarray(ids, dtype=int)
        per_row = self.squares[0] - 1
        grid = np.stack([ids % per_row + 1, ids // per_row + 1], axis=1).astype(np.float64)
        return np.asarray(self.origin_uv, dtype=np.float64) + self.square_px * grid

    def outline_uv(self) -> np.ndarray:
        """(4, 2) (u, v) of the board's outer corners: top-left, top-right, bottom-right, bottom-left."""
        nx, ny = self.squares
        return np.asarray(self.origin_uv) + self.square_px * np.array([[0, 0], [nx, 0], [nx, ny], [0, ny]], float)

    def to_json(self, mm_per_unit: float | None = None) -> dict[str, Any]:
        out = {"dictionary": self.dictionary, "squares": list(self.squares), "square_px": self.square_px,
               "marker_px": self.marker_px, "first_id": self.first_id, "origin_uv": list(self.origin_uv)}
        if mm_per_unit is not None:
            out["square_mm"] = round(self.square_px * mm_per_unit, 4)
            out["marker_mm"] = round(self.marker_px * mm_per_unit, 4)
        if self.legacy:
            out["legacy"] = True
        return out


@dataclass(frozen=True)
class Face:
    """One face: pixel (u, v) of ``image`` lies at ``origin + u * u_axis + v * v_axis`` (mm)."""
    index: int
    image: Path | None  # the printable page; None for a target described by numbers only
    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    board: Board
    size_px: tuple[int, int] | None = None  # (width, height) of the image, when known

    @property
    def normal(self) -> np.ndarray:
        """Unit normal pointing to where the printed side is seen from: -(u x v)."""
        n = -np.cross(self.u_axis, self.v_axis)
        return n / np.linalg.norm(n)

    def to_3d(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) face-image (u, v) -> (N, 3) points in the target's frame (mm)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return self.origin + uv[:, :1] * self.u_axis + uv[:, 1:] * self.v_axis

    def matrix(self) -> np.ndarray:
        """The 4x3 matrix taking (u, v, 1) to homogeneous 3D (X, Y, Z, 1): ``P @ matrix()`` is the
        homography from the face image to a camera image."""
        M = np.zeros((4, 3))
        M[:3, 0], M[:3, 1], M[:3, 2], M[3, 2] = self.u_axis, self.v_axis, self.origin, 1.0
        return M

    def seen_from(self, centre: np.ndarray) -> bool:
        """True when a camera centred at ``centre`` (mm) faces the printed side."""
        return bool((np.asarray(centre, float) - self.origin) @ self.normal > 0)

    def corners3d(self) -> np.ndarray:
        """(n_corners, 3) 3D points of every chessboard corner, in corner-id order."""
        return self.to_3d(self.board.corner_uv())

    def moved(self, R: np.ndarray, t: np.ndarray) -> "Face":
        """This face after the rigid motion X -> R X + t of its points (a refined face pose)."""
        return replace(self, origin=R @ self.origin + t, u_axis=R @ self.u_axis, v_axis=R @ self.v_axis)


@dataclass(frozen=True)
class Target:
    path: Path
    faces: list[Face]
    unit: str = "mm"
    planar: bool = False  # every board on one plane: a flat target

    def moved(self, poses: list[tuple[np.ndarray, np.ndarray]]) -> "Target":
        """The target with face k moved by poses[k] = (R, t) (:meth:`Face.moved`)."""
        return replace(self, faces=[f.moved(R, t) for f, (R, t) in zip(self.faces, poses)])


def target_json(target: Target, relative_to: Path | None = None, note: str | None = None) -> dict[str, Any]:
    """The ``target.json`` object of ``target`` (face images named relative to ``relative_to``,
    the folder it will be written into; a face image elsewhere is named by its absolute path)."""
    faces = []
    for f in target.faces:
        entry: dict[str, Any] = {}
        if f.image is not None:
            image = Path(f.image).resolve()
            try:
                entry["image"] = str(image.relative_to(Path(relative_to).resolve())) if relative_to else str(image)
            except ValueError:
                entry["image"] = str(image)
        if f.size_px is not None:
            entry["size_px"] = list(f.size_px)
        entry.update({"origin": (f.origin + 0.0).tolist(), "u_axis": (f.u_axis + 0.0).tolist(),
                      "v_axis": (f.v_axis + 0.0).tolist(),
                      "board": f.board.to_json(float(np.linalg.norm(f.u_axis)))})
        faces.append(entry)
    out: dict[str, Any] = {"unit": target.unit}
    if note:
        out["note"] = note
    out["faces"] = faces
    return out


# ---------------------------------------------------------------- loading
def _vector(value: Any, n: int, where: str) -> np.ndarray:
    ok = (isinstance(value, list) and len(value) == n
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value))
    arr = np.array(value, dtype=np.float64) if ok else None
    if arr is None or not np.all(np.isfinite(arr)) or np.abs(arr).max(initial=0) > 1e9:
        raise StereoseedError(f"{where}: expected a list of {n} finite numbers; fix target.json")
    return arr


def _int(value: Any, where: str, low: int) -> int:
    if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
            or value != int(value) or value < low):
        raise StereoseedError(f"{where}: expected a whole number >= {low}; fix target.json")
    return int(value)


def _flag(value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        raise StereoseedError(f"{where}: expected true or false; fix target.json")
    return value


def _board(spec: Any, where: str, legacy: bool) -> Board:
    if not isinstance(spec, dict):
        raise StereoseedError(f"{where}: expected an object (dictionary, squares, square_px, marker_px, first_id, "
                              "origin_uv); fix target.json")
    missing = [k for k in ("dictionary", "squares", "square_px", "marker_px", "first_id", "origin_uv") if k not in spec]
    if missing:
        raise StereoseedError(f"{where}: missing {', '.join(missing)}; fix target.json")
    name = spec["dictionary"]
    if not (isinstance(name, str) and name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)):
        raise StereoseedError(f"{where}.dictionary: not an ArUco dictionary of OpenCV (e.g. DICT_5X5_1000); "
                              "fix target.json")
    sq = spec["squares"]
    if not (isinstance(sq, list) and len(sq) == 2):
        raise StereoseedError(f"{where}.squares: expected [nx, ny]; fix target.json")
    squares = (_int(sq[0], f"{where}.squares", 3), _int(sq[1], f"{where}.squares", 3))
    square, marker = (_vector([spec[k]], 1, f"{where}.{k}")[0] for k in ("square_px", "marker_px"))
    if not 0 < marker < square:
        raise StereoseedError(f"{where}: needs 0 < marker_px < square_px; fix target.json")
    if "legacy" in spec:
        legacy = _flag(spec["legacy"], f"{where}.legacy")
    board = Board(name, squares, float(square), float(marker), _int(spec["first_id"], f"{where}.first_id", 0),
                  tuple(_vector(spec["origin_uv"], 2, f"{where}.origin_uv").tolist()), legacy)
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if board.first_id + board.n_markers > size:
        raise StereoseedError(f"{where}: marker ids {board.first_id}..{board.first_id + board.n_markers - 1} "
                              f"beyond {name}'s {size} markers; fix target.json")
    return board


def _face(spec: Any, k: int, path: Path, legacy: bool) -> Face:
    where = f"{path}: faces[{k}]"
    if not isinstance(spec, dict):
        raise StereoseedError(f"{where}: expected an object; fix target.json")
    missing = [key for key in ("origin", "u_axis", "v_axis", "board") if key not in spec]
    if missing:
        raise StereoseedError(f"{where}: missing {', '.join(missing)}; fix target.json")
    image = None
    if "image" in spec:  # the printable page: needed to print or render the face, not to find it
        if not isinstance(spec["image"], str) or not spec["image"]:
            raise StereoseedError(f"{where}.image: expected the face image's file name; fix target.json")
        image = path.parent / spec["image"]
        if not image.is_file():
            raise StereoseedError(f"{path}: face {k} image {image} not found; keep the face images beside "
                                  "target.json (or leave \"image\" out)")
    origin, u, v = (_vector(spec[key], 3, f"{where}.{key}") for key in ("origin", "u_axis", "v_axis"))
    nu, nv = np.linalg.norm(u), np.linalg.norm(v)
    if nu == 0 or nv == 0 or np.linalg.norm(np.cross(u, v)) < 1e-3 * nu * nv:
        raise StereoseedError(f"{where}: u_axis and v_axis must be non-zero and not parallel (the size and "
                              "direction of a pixel step on the face); fix target.json")
    size = spec.get("size_px")
    size_px = None
    if size is not None:
        s = _vector(size, 2, f"{where}.size_px")
        size_px = (_int(s[0], f"{where}.size_px", 1), _int(s[1], f"{where}.size_px", 1))
    return Face(k, image, origin, u, v, _board(spec["board"], f"{where}.board", legacy), size_px)


def load_target(path: str | os.PathLike) -> Target:
    """Read and check ``target.json`` (module doc); face images are relative to its folder."""
    path = Path(path)
    if path.is_dir():
        path = path / "target.json"
    if not path.is_file():
        raise StereoseedError(f"{path}: target file not found; run stereoseed target --out DIR first, "
                              "or give DIR/target.json")
    try:
        data = json.loads(read_bounded_text(path, "target file", "give the target.json written by stereoseed target",
                                            "utf-8-sig"))
    except (OSError, UnicodeDecodeError, ValueError) as e:
        detail = f" (line {e.lineno})" if isinstance(e, json.JSONDecodeError) else ""
        raise StereoseedError(f"{path}: not a readable JSON target{detail}; give the target.json written by "
                              "stereoseed target") from None
    if not isinstance(data, dict) or not isinstance(data.get("faces"), list):
        raise StereoseedError(f'{path}: expected {{"unit": "mm", "faces": [...]}}; give the target.json written '
                              "by stereoseed target")
    unit = data.get("unit", "mm")
    if not isinstance(unit, str):
        raise StereoseedError(f"{path}: unit: expected a string such as \"mm\"; fix target.json")
    if not data["faces"]:
        raise StereoseedError(f"{path}: no faces; a target needs at least one board")
    legacy = _flag(data["legacy"], f"{path}: legacy") if "legacy" in data else False
    faces = [_face(spec, k, path, legacy) for k, spec in enumerate(data["faces"])]
    seen: dict[tuple[str, int], int] = {}
    for f in faces:
        for i in range(f.board.first_id, f.board.first_id + f.board.n_markers):
            other = seen.setdefault((f.board.dictionary, i), f.index)
            if other != f.index:
                raise StereoseedError(f"{path}: faces {other} and {f.index} share marker id {i}; give each face its "
                                      "own first_id range")
    points = np.concatenate([f.to_3d(f.board.outline_uv()) for f in faces])
    spread = np.linalg.svd(points - points.mean(0), compute_uv=False)
    planar = bool(spread[2] <= _COPLANAR_RATIO * spread[0])
    if planar:
        log.debug("%s: every board lies on one plane: a flat target", path)
    return Target(path, faces, unit, planar)
