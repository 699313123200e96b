"""A printable 3D calibration target (ChArUco boards on 2 or 3 faces of a box) and its detection.

Making it: :func:`make_target` writes one PNG per face (300 dpi, the board centred on the page with
margins; the face index, "print at 100 %, do not scale" and a 100 mm check bar in the margins), an
assembly sheet ``assembly.png`` and ``target.json``. Detecting it: :func:`load_target` then
:func:`detect_target` give 3D points (mm) and their sub-pixel image positions, for a DLT / LM
calibration of a camera.

The contract of ``target.json``
-------------------------------
::

    {"unit": "mm",
     "faces": [{"image": "face_0.png", "size_px": [W, H],
                "origin": [x, y, z], "u_axis": [..], "v_axis": [..],
                "board": {"dictionary": "DICT_5X5_1000", "squares": [nx, ny],
                          "square_px": 350, "marker_px": 252, "first_id": 0,
                          "origin_uv": [u0, v0], "square_mm": .., "marker_mm": ..}}, ...]}

* The centre of pixel (u, v) of a face image lies at ``origin + u * u_axis + v * v_axis`` in the
  target's frame (mm). Pixel convention: (0, 0) is the centre of the top-left pixel (as OpenCV),
  so the outer edge of the image is at u = -0.5 and u = W - 0.5.
* The printed side is seen from the side ``-(u_axis x v_axis)`` points to (u to the right, v down
  on the page, u x v points into the page, away from whoever reads it).
* ``board``: the ChArUco board inside the face image. ``origin_uv`` is the (u, v) of the board's
  outer top-left corner, a point between pixels (so half-integer for a generated target: the
  board's first pixel column starts at u = origin_u + 0.5). Chessboard (ChArUco) corner ``k``
  (OpenCV's numbering, row by row from the top-left inner corner, ``nx - 1`` per row) lies at
  ``origin_uv + square_px * (k % (nx - 1) + 1, k // (nx - 1) + 1)``; its 3D point follows from the
  contract above. The markers have ids ``first_id .. first_id + nx * ny // 2 - 1`` (OpenCV's
  current, non-legacy ChArUco layout: the top-left square is black); no two faces share an id.
  ``square_mm`` / ``marker_mm`` are for people (``square_px * |u_axis|``); the loader ignores them.

A hand-written ``target.json`` for a measured, non-ideal box may give any origin / u_axis /
v_axis per face (faces not square to each other, a printer that scaled by 0.98, ...).

The frame of a generated target
-------------------------------
A convex box corner at the origin, the box in the negative octant, z up. The printed sides face
outwards, into the positive octant: a camera at e.g. (400, 400, 400) mm looking at the origin
sees every face. Each sheet's paper corner sits on the box corner:

* face 0 on the side x = 0 (normal +x): u along +y, v along -z (upright); its right paper edge on
  the vertical box edge (x = y = 0), its top edge on the top edge. It covers y in [-W, 0],
  z in [-H, 0] (W, H the page size in mm).
* face 1 on the side y = 0 (normal +y): u along -x, v along -z; its left paper edge on the vertical
  box edge, its top edge on the top edge. It covers x in [-W, 0], z in [-H, 0].
* face 2 (3 faces only) on the top z = 0 (normal +z): u along -x, v along +y; its left paper edge on
  face 0's top edge, its bottom paper edge on face 1's top edge. It covers x in [-W, 0], y in [-H, 0].

So the box needs at least W x H x H mm (x, y, z; W x W x H with 2 faces). A camera at C sees the printed side of
a face when ``(C - origin) . normal > 0``; the box being convex, faces it sees do not hide each
other. A printer does not put the page exactly where the paper is: measure where the boards
ended up and edit ``target.json`` when the calibration must be exact.
"""
from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_image, write_image, write_json

log = logging.getLogger(__name__)

__all__ = ["make_target", "load_target", "detect_target", "Target", "Face", "Board", "Detection",
           "PAPER_MM", "DPI"]

DPI = 300
MM_PER_PX = 25.4 / DPI
# paper sizes, portrait (width, height) in mm
PAPER_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "letter": (215.9, 279.4)}
# square size in print pixels: 413 px = 35.0 mm on A4 / letter (5 x 7 squares), 581 px = 49.2 mm on
# A3 (5 x 8); the marker is ~70 % of it, a whole number of its 7 cells (5 x 5 bits, a 1-bit border):
# a 640x480 photo at ~0.5 m still gives each cell ~2 px on a face seen at 55 degrees, and the white
# margin around each chessboard corner stays wide enough for its sub-pixel fit
_SQUARE_PX = {"A4": 413, "A3": 581, "letter": 413}
_MARKER_RATIO = 0.7
_MARKER_CELLS = 7
_MIN_MARGIN_PX = round(12 / MM_PER_PX)  # at least 12 mm of paper around the board for the text
DICTIONARY = "DICT_5X5_1000"
MIN_FACE_CORNERS = 4  # corners a face needs to count as found (fewer: dropped)
MIN_CORNERS = 12  # corners an image needs in all
_COPLANAR_RATIO = 1e-3  # smallest / largest spread of the corners' 3D points below this: coplanar


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

    @property
    def n_markers(self) -> int:
        return self.squares[0] * self.squares[1] // 2

    @property
    def n_corners(self) -> int:
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        ids = np.arange(self.first_id, self.first_id + self.n_markers, dtype=np.int32)
        return cv2.aruco.CharucoBoard(self.squares, float(self.square_px), float(self.marker_px), d, ids)

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


@dataclass(frozen=True)
class Face:
    """One face: pixel (u, v) of ``image`` lies at ``origin + u * u_axis + v * v_axis`` (mm)."""
    index: int
    image: Path
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


@dataclass(frozen=True)
class Target:
    path: Path
    faces: list[Face]
    unit: str = "mm"


@dataclass
class Detection:
    """The target corners found in one image."""
    points3d: np.ndarray  # (N, 3) in the target's frame (mm)
    pixels: np.ndarray  # (N, 2), (0, 0) the centre of the top-left pixel
    face: np.ndarray  # (N,) face index
    ids: np.ndarray  # (N,) ChArUco corner id within its face
    counts: list[int] = field(default_factory=list)  # corners per face (all faces, found or not)

    def __len__(self) -> int:
        return len(self.ids)


# ---------------------------------------------------------------- making the target
def _page_px(size: str) -> tuple[int, int]:
    w, h = PAPER_MM[size]
    return round(w / MM_PER_PX), round(h / MM_PER_PX)


def _face_geometry(k: int, W: int, H: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """origin, u_axis, v_axis and a plane label of face ``k`` of a generated target (module doc)."""
    p = MM_PER_PX
    ex, ey, ez = np.eye(3)
    if k == 0:  # side x = 0, u along +y, v along -z, right paper edge at y = 0
        return np.array([0.0, -(W - 0.5) * p, -0.5 * p]), p * ey, -p * ez, "x = 0"
    if k == 1:  # side y = 0, u along -x, v along -z, left paper edge at x = 0
        return np.array([-0.5 * p, 0.0, -0.5 * p]), -p * ex, -p * ez, "y = 0"
    # top z = 0, u along -x, v along +y: left paper edge at x = 0, bottom paper edge at y = 0
    return np.array([-0.5 * p, -(H - 0.5) * p, 0.0]), -p * ex, p * ey, "z = 0, top"


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, thickness: int = 2,
          colour: int | tuple = 0) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA)


def _face_image(board: Board, W: int, H: int, k: int, n_faces: int, label: str) -> np.ndarray:
    page = np.full((H, W), 255, np.uint8)
    nx, ny = board.squares
    sq = int(board.square_px)
    x0, y0 = round(board.origin_uv[0] + 0.5), round(board.origin_uv[1] + 0.5)
    page[y0:y0 + ny * sq, x0:x0 + nx * sq] = board.cv_board().generateImage((nx * sq, ny * sq), marginSize=0,
                                                                            borderBits=1)
    # the margin texts: ~2.5 mm tall, centred in the top and bottom margins, never on the board
    scale, th = 1.0, 2
    top = f"stereoseed target: face {k} of {n_faces} (side {label}), this edge up - print at 100 %, do not scale"
    (tw, tht), _ = cv2.getTextSize(top, cv2.FONT_HERSHEY_SIMPLEX, scale, th)
    _text(page, top, (max(10, (W - tw) // 2), (y0 + tht) // 2), scale, th)
    bar = round(100 / MM_PER_PX)
    yb = y0 + ny * sq + (H - y0 - ny * sq) // 2
    cv2.rectangle(page, (x0, yb - 6), (x0 + bar - 1, yb + 5), 0, -1)
    _text(page, f"100 mm (check with a ruler) - face {k}", (x0 + bar + 30, yb + tht // 2), scale, th)
    return page


def _make_board(size: str, W: int, H: int, first_id: int) -> Board:
    sq = _SQUARE_PX[size]
    nx, ny = (W - 2 * _MIN_MARGIN_PX) // sq, (H - 2 * _MIN_MARGIN_PX) // sq
    marker = int(sq * _MARKER_RATIO) // _MARKER_CELLS * _MARKER_CELLS
    x0, y0 = (W - nx * sq) // 2, (H - ny * sq) // 2
    return Board(DICTIONARY, (nx, ny), float(sq), float(marker), first_id, (x0 - 0.5, y0 - 0.5))


def make_target(out_dir: str | os.PathLike, size: str = "A4", faces: int = 3) -> Path:
    """Write the printable target into ``out_dir``: ``face_<k>.png`` (300 dpi), ``assembly.png``
    and ``target.json`` (module doc). Returns the path of ``target.json``."""
    if size not in PAPER_MM:
        raise StereoseedError(f"--size {size}: unknown paper size; give one of {', '.join(PAPER_MM)}")
    if faces not in (2, 3):
        raise StereoseedError(f"--faces {faces}: the target has 2 or 3 faces")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise StereoseedError(f"{out}: is a file; give a folder to write the target into")
    W, H = _page_px(size)
    entries, face_objs, pages = [], [], []
    first_id = 0
    for k in range(faces):
        board = _make_board(size, W, H, first_id)
        first_id += board.n_markers
        origin, u, v, label = _face_geometry(k, W, H)
        name = f"face_{k}.png"
        pages.append(_face_image(board, W, H, k, faces, label))
        write_image(out / name, pages[-1])
        face_objs.append(Face(k, out / name, origin, u, v, board, (W, H)))
        entries.append({
            "image": name, "size_px": [W, H], "plane": label,
            "origin": (origin + 0.0).tolist(), "u_axis": (u + 0.0).tolist(), "v_axis": (v + 0.0).tolist(),
            "board": {"dictionary": board.dictionary, "squares": list(board.squares),
                      "square_px": board.square_px, "marker_px": board.marker_px, "first_id": board.first_id,
                      "origin_uv": list(board.origin_uv),
                      "square_mm": round(board.square_px * MM_PER_PX, 4),
                      "marker_mm": round(board.marker_px * MM_PER_PX, 4)}})
    write_image(out / "assembly.png", _assembly_sheet(face_objs, pages, size, W, H))
    path = write_json(out / "target.json", {
        "unit": "mm", "paper": size, "dpi": DPI,
        "note": "pixel (u, v) centre of a face image (0, 0 = centre of the top-left pixel) lies at "
                "origin + u * u_axis + v * v_axis (mm); the printed side faces -(u_axis x v_axis)",
        "faces": entries})
    log.info("wrote a %d-face %s target into %s", faces, size, out)
    return path


def _assembly_sheet(faces: list[Face], pages: list[np.ndarray], size: str, W: int, H: int) -> np.ndarray:
    """A landscape page: the target seen from (1, 1, 1) (an axonometric view textured with the
    face images through the contract), the axes, and the instructions."""
    SW, SH = _page_px("A4")[::-1] if size != "letter" else _page_px("letter")[::-1]
    sheet = np.full((SH, SW, 3), 255, np.uint8)
    right = np.array([-1.0, 1.0, 0.0]) / math.sqrt(2)
    down = np.array([1.0, 1.0, -2.0]) / math.sqrt(6)
    wmm, hmm = W * MM_PER_PX, H * MM_PER_PX
    ymm = hmm if len(faces) == 3 else wmm  # the smallest box the sheets fit on (module doc)
    box = np.array([[x, y, z] for x in (-wmm, 0) for y in (-ymm, 0) for z in (-hmm, 0)])
    extent = np.stack([box @ right, box @ down], 1)
    area = (SW * 0.5, SH * 0.78)  # the drawing's room, left part of the page
    s = 0.8 * min(area[0] / np.ptp(extent[:, 0]), area[1] / np.ptp(extent[:, 1]))  # px per mm
    c = np.array([SW * 0.27, SH * 0.55]) - s * extent.mean(0)
    A = np.zeros((3, 4))
    A[0, :3], A[1, :3], A[:2, 3], A[2, 3] = s * right, s * down, c, 1.0  # affine camera

    def proj(X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        return (X @ A[:2, :3].T + A[:2, 3]).astype(np.float64)

    # the box edges (behind the faces)
    for i, a in enumerate(box):
        for b in box[i + 1:]:
            if np.count_nonzero(a != b) == 1:
                pa, pb = proj(a)[0], proj(b)[0]
                cv2.line(sheet, tuple(int(round(t)) for t in pa), tuple(int(round(t)) for t in pb), (170, 170, 170), 3,
                         cv2.LINE_AA)
    f = 4  # the face images reduced 4x first (a reduced pixel u' is centred on u = f u' + (f - 1) / 2)
    reduce = np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1.0]])
    for face, img in zip(faces, pages):  # the pages as drawn (grey), not read back from their PNGs
        small = cv2.resize(img, (img.shape[1] // f, img.shape[0] // f), interpolation=cv2.INTER_AREA)
        Hm = A @ face.matrix() @ reduce
        warped = cv2.warpPerspective(small, Hm, (SW, SH), flags=cv2.INTER_LINEAR, borderValue=0)
        mask = cv2.warpPerspective(np.full_like(small, 255), Hm, (SW, SH), flags=cv2.INTER_NEAREST, borderValue=0)
        tint = np.array([(255, 225, 225), (225, 255, 225), (225, 225, 255)][face.index % 3], np.float64) / 255
        sheet[mask > 0] = (warped[mask > 0, None] * tint).astype(np.uint8)
        mid = proj(face.to_3d(np.array([[W / 2, H / 2]])))[0]
        label = f"face {face.index}"
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 3, 8)
        org = (int(mid[0] - tw / 2), int(mid[1] + th / 2))
        cv2.rectangle(sheet, (org[0] - 15, org[1] - th - 15), (org[0] + tw + 15, org[1] + 20), (255, 255, 255), -1)
        _text(sheet, label, org, 3, 8, (0, 0, 200))
    # the axes from the box corner, out of the box
    o = proj(np.zeros(3))[0]
    for axis, name, colour in ((0, "x", (0, 0, 220)), (1, "y", (0, 160, 0)), (2, "z", (220, 0, 0))):
        e = np.zeros(3)
        e[axis] = 120.0
        tip = proj(e)[0]
        cv2.arrowedLine(sheet, tuple(int(t) for t in o), tuple(int(t) for t in tip), colour, 10, cv2.LINE_AA,
                        tipLength=0.15)
        _text(sheet, name, (int(tip[0] + 15), int(tip[1] + 15)), 3, 8, colour)
    _text(sheet, "0", (int(o[0] + 15), int(o[1] - 20)), 2, 5)
    n = len(faces)
    wm, ym, hm = round(wmm), round(ymm), round(hmm)
    lines = [
        f"stereoseed 3D calibration target: {n} faces, {size}",
        "",
        f"1. Print face_0.png .. face_{n - 1}.png at 100 % (no scaling, no 'fit to page').",
        "   Check the 100 mm bar on each sheet with a ruler.",
        f"2. Take a box of at least {wm} x {ym} x {hm} mm (x, y, z; z up).",
        "   Its corner is the origin 0, z up; the box is on the negative side of each axis.",
        "3. Glue each sheet flat, its paper corner on the box corner as drawn:",
        "   face 0 on the side x = 0: right paper edge on the vertical box edge, top edge up;",
        "   face 1 on the side y = 0: left paper edge on the vertical box edge, top edge up;",
    ]
    if n == 3:
        lines += ["   face 2 on the top z = 0: left paper edge on face 0's top edge,",
                  "   bottom paper edge on face 1's top edge."]
    lines += [
        "4. Photograph the corner so that at least two faces show, whole, sharp and well lit.",
        "",
        "target.json: pixel (u, v) of face_k.png lies at origin + u * u_axis + v * v_axis (mm).",
        "For an exact calibration measure where the boards ended up on the box",
        "(printers shift the page by a mm or so) and edit target.json.",
    ]
    y = int(SH * 0.07)
    for line in lines:
        _text(sheet, line, (int(SW * 0.50), y), 1.35, 3)
        y += 70
    return sheet


# ---------------------------------------------------------------- loading
def _vector(value: Any, n: int, where: str) -> np.ndarray:
    ok = (isinstance(value, list) and len(value) == n
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value))
    arr = np.array(value, dtype=np.float64) if ok else None
    if arr is None or not np.all(np.isfinite(arr)) or np.abs(arr).max(initial=0) > 1e9:
        raise StereoseedError(f"{where}: expected a list of {n} finite numbers; fix target.json")
    return arr


def _int(value: Any, where: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) or value < low:
        raise StereoseedError(f"{where}: expected a whole number >= {low}; fix target.json")
    return int(value)


def _board(spec: Any, where: str) -> Board:
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
    board = Board(name, squares, float(square), float(marker), _int(spec["first_id"], f"{where}.first_id", 0),
                  tuple(_vector(spec["origin_uv"], 2, f"{where}.origin_uv").tolist()))
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if board.first_id + board.n_markers > size:
        raise StereoseedError(f"{where}: marker ids {board.first_id}..{board.first_id + board.n_markers - 1} "
                              f"beyond {name}'s {size} markers; fix target.json")
    return board


def load_target(path: str | os.PathLike) -> Target:
    """Read and check ``target.json`` (module doc); face images are relative to its folder."""
    path = Path(path)
    if path.is_dir():
        path = path / "target.json"
    if not path.is_file():
        raise StereoseedError(f"{path}: target file not found; run stereoseed target --out DIR first, "
                              "or give DIR/target.json")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
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
    if len(data["faces"]) < 2:
        raise StereoseedError(f"{path}: {len(data['faces'])} face(s); a 3D target needs at least 2 faces "
                              "on different planes")
    faces = []
    for k, spec in enumerate(data["faces"]):
        where = f"{path}: faces[{k}]"
        if not isinstance(spec, dict):
            raise StereoseedError(f"{where}: expected an object; fix target.json")
        missing = [key for key in ("image", "origin", "u_axis", "v_axis", "board") if key not in spec]
        if missing:
            raise StereoseedError(f"{where}: missing {', '.join(missing)}; fix target.json")
        if not isinstance(spec["image"], str) or not spec["image"]:
            raise StereoseedError(f"{where}.image: expected the face image's file name; fix target.json")
        image = path.parent / spec["image"]
        if not image.is_file():
            raise StereoseedError(f"{path}: face {k} image {image} not found; keep the face images beside "
                                  "target.json")
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
        faces.append(Face(k, image, origin, u, v, _board(spec["board"], f"{where}.board"), size_px))
    seen: dict[tuple[str, int], int] = {}
    for f in faces:
        for i in range(f.board.first_id, f.board.first_id + f.board.n_markers):
            other = seen.setdefault((f.board.dictionary, i), f.index)
            if other != f.index:
                raise StereoseedError(f"{path}: faces {other} and {f.index} share marker id {i}; give each face its "
                                      "own first_id range")
    points = np.concatenate([f.to_3d(f.board.outline_uv()) for f in faces])
    spread = np.linalg.svd(points - points.mean(0), compute_uv=False)
    if spread[2] <= _COPLANAR_RATIO * spread[0]:
        raise StereoseedError(f"{path}: the faces are coplanar (all boards on one plane); a 3D target needs boards "
                              "on at least two different planes: fix each face's origin / u_axis / v_axis")
    return Target(path, faces, unit)


# ---------------------------------------------------------------- detection
_SADDLE_HALF = 2  # the saddle fit's window: (2 * half + 1)^2 pixels
_SADDLE_SIGMA = 1.0  # Gaussian blur before the fit, pixels
_SADDLE_MOVE = 1.5  # a corner the fit moves further than this (pixels) from OpenCV's is dropped
_ys, _xs = np.mgrid[-_SADDLE_HALF:_SADDLE_HALF + 1, -_SADDLE_HALF:_SADDLE_HALF + 1].reshape(2, -1).astype(np.float64)
_SADDLE_FIT = np.linalg.pinv(np.stack([_xs * _xs, _xs * _ys, _ys * _ys, _xs, _ys, np.ones_like(_xs)], axis=1))


def _refine_saddles(blurred: np.ndarray, points: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Chessboard corners refined as the saddle point of a quadratic fitted to the blurred image
    around each (Newton steps); (refined (N, 2), ok (N,)). cornerSubPix's gradient window reaches
    the marker borders next to a corner on an oblique face and is pulled by up to ~2 px there; a
    5x5 saddle fit stays on the X junction. A corner that is no saddle, does not converge or
    moves more than ``_SADDLE_MOVE`` px is not ok."""
    size = (2 * _SADDLE_HALF + 1,) * 2
    out, ok = points.astype(np.float64).copy(), np.zeros(len(points), bool)
    for i, start in enumerate(out):
        p = start.copy()
        for _ in range(iterations):
            patch = cv2.getRectSubPix(blurred, size, (float(p[0]), float(p[1]))).reshape(-1).astype(np.float64)
            a, b, c, d, e, _ = _SADDLE_FIT @ patch
            det = 4 * a * c - b * b
            if not det < -1e-12 * (a * a + b * b + c * c + 1e-30):  # no saddle (or flat)
                break
            step = np.array([-2 * c * d + b * e, b * d - 2 * a * e]) / det  # Hessian^-1 @ -gradient
            p += step
            if np.linalg.norm(p - start) > _SADDLE_MOVE:
                break
            if step @ step < 1e-6:  # converged; a slow one (marker edges in the window) is left out
                ok[i] = True
                break
        out[i] = p
    return out, ok


def _grey(image: np.ndarray, what: str) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise StereoseedError(f"{what}: expected an 8-bit grey or colour image; convert it to 8 bits")
    if image.ndim == 3:
        channels = image.shape[2]
        image = image[:, :, 0] if channels == 1 else cv2.cvtColor(
            image, cv2.COLOR_BGR2GRAY if channels == 3 else cv2.COLOR_BGRA2GRAY)
    return np.ascontiguousarray(image)


def detect_target(image: np.ndarray | str | os.PathLike, target: Target, what: str | None = None) -> Detection:
    """The target's ChArUco corners in ``image`` (an array, or a path read with
    :func:`stereoseed.io.files.read_image`), with their 3D points. ``what`` names the image in messages.

    Markers are detected once per dictionary and each face's markers (its id range) go to its
    :class:`cv2.aruco.CharucoDetector` (corners interpolated then refined to sub-pixel). A face
    with fewer than ``MIN_FACE_CORNERS`` corners is dropped. Refused (one line): no target, a
    single face, fewer than ``MIN_CORNERS`` corners in all."""
    if not isinstance(image, np.ndarray):
        what = what or str(image)
        image = read_image(image)
    what = what or "image"
    grey = _grey(image, what)
    blurred = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), _SADDLE_SIGMA)
    markers: dict[str, tuple[tuple, np.ndarray]] = {}
    for name in {f.board.dictionary for f in target.faces}:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        corners, ids, _ = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters()).detectMarkers(grey)
        markers[name] = (corners, np.empty(0, int) if ids is None else ids.ravel())
    pts3d, pix, face_idx, corner_ids, counts = [], [], [], [], []
    for f in target.faces:
        corners, ids = markers[f.board.dictionary]
        mine = np.flatnonzero((ids >= f.board.first_id) & (ids < f.board.first_id + f.board.n_markers))
        cc = None
        if len(mine) >= 2:
            detector = cv2.aruco.CharucoDetector(f.board.cv_board())
            cc, ci, _, _ = detector.detectBoard(grey, markerCorners=tuple(corners[i] for i in mine),
                                                markerIds=ids[mine].reshape(-1, 1).astype(np.int32))
        n = 0
        if cc is not None and len(cc):
            refined, ok = _refine_saddles(blurred, cc.reshape(-1, 2))
            if not ok.all():
                log.debug("%s: face %d: %d corners dropped (no clean saddle point)", what, f.index, (~ok).sum())
            cc, ci, n = refined[ok], ci.ravel()[ok], int(ok.sum())
        if 0 < n < MIN_FACE_CORNERS:
            log.debug("%s: face %d: only %d corners, dropped", what, f.index, n)
            n = 0
        counts.append(n)
        if n:
            ci = ci.astype(int)
            pts3d.append(f.to_3d(f.board.corner_uv(ci)))
            pix.append(cc)
            face_idx.append(np.full(n, f.index))
            corner_ids.append(ci)
    found = [k for k, n in enumerate(counts) if n]
    if not found:
        raise StereoseedError(f"{what}: no calibration target found; show the whole target, well lit, sharp")
    if len(found) == 1:
        raise StereoseedError(f"{what}: only face {found[0]} of the target was found; show at least two faces")
    total = sum(counts)
    if total < MIN_CORNERS:
        raise StereoseedError(f"{what}: only {total} target corners found (at least {MIN_CORNERS} needed); come "
                              "closer so the faces fill more of the image, sharp and well lit")
    log.debug("%s: %d target corners (%s per face)", what, total, counts)
    return Detection(np.concatenate(pts3d), np.concatenate(pix), np.concatenate(face_idx),
                     np.concatenate(corner_ids), counts)
