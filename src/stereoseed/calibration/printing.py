"""Printing a 3D calibration target: ChArUco boards for 2 or 3 faces of a box.

:func:`make_target` writes, per face, ``face_<k>.png`` (300 dpi, its resolution in the PNG's pHYs
chunk so that a viewer prints it at true size) and ``face_<k>.pdf`` (the same page at true scale:
print it at 100 %), an assembly sheet ``assembly.png`` and ``target.json``
(:mod:`stereoseed.calibration.target`). Each page: the board centred with margins, the face
index, "print at 100 %, do not scale" and a 100 mm check bar.

The frame of a generated target
-------------------------------
A convex box corner at the origin, the box in the negative octant, z up. The printed sides face
outwards, into the positive octant: a camera at e.g. (400, 400, 400) mm looking at the origin
sees every face. Each sheet's paper corner sits on the box corner:

* face 0 on the side x = 0 (normal +x): u along +y, v along -z (upright); its right paper edge on
  the vertical box edge (x = y = 0), its top edge on the top edge. It covers y in [-W, 0],
  z in [-H, 0] (W, H the page size in mm).
* face 1 on the side y = 0 (normal +y): u along -x, v along -z; its left paper edge on the vertical
  box edge. It covers x in [-W, 0], z in [-H, 0].
* face 2 (3 faces only) on the top z = 0 (normal +z): u along -x, v along +y; its left paper edge on
  face 0's top edge, its bottom paper edge on face 1's top edge. It covers x in [-W, 0], y in [-H, 0].

So the box needs at least W x H x H mm (x, y, z; W x W x H with 2 faces): :func:`box_size_mm`.
A camera at C sees the printed side of a face when ``(C - origin) . normal > 0``; the box being
convex, faces it sees do not hide each other. A printer does not put the page exactly where the
paper is: the calibration estimates where each face ended up (or measure and edit target.json).
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from stereoseed.calibration.target import Board, Face, Target, target_json
from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import atomic_path, jsonable
from stereoseed.io.outputs import OwnedFiles

log = logging.getLogger(__name__)

__all__ = ["make_target", "box_size_mm", "png_with_dpi", "pdf_page", "PAPER_MM", "DPI", "DICTIONARY"]

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
# what `target --out` writes: a folder holding anything else is someone else's, refused
_OURS = re.compile(r"(face_\d+\.(png|pdf)|assembly\.png|target\.json)")
# the record of the files `target` wrote, with their hashes: only those are ever replaced or removed
TARGET_RECORD = ".stereoseed-target.json"


# ---------------------------------------------------------------- true-scale files
def png_with_dpi(image: np.ndarray, dpi: float) -> bytes:
    """``image`` encoded as PNG with its resolution in a pHYs chunk (pixels per metre), which
    cv2.imencode does not write: without it a viewer guesses 72 or 96 dpi and prints the page 3-4
    times too large. The chunk goes right after IHDR, before the image data (PNG spec 11.3.5.3)."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise StereoseedError("OpenCV could not encode the page as PNG")
    data = data.tobytes()
    ppm = round(dpi / 0.0254)
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)  # unit 1: the metre
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    ihdr_end = 8 + 8 + 13 + 4  # signature, IHDR length + type, IHDR data, CRC
    return data[:ihdr_end] + chunk + data[ihdr_end:]


def pdf_page(grey: np.ndarray, dpi: float) -> bytes:
    """A one-page PDF holding the 8-bit grey ``grey`` at ``dpi``: the page is the image's size
    (a 300 dpi A4 page is 595 x 842 pt), so printing it at 100 % gives true scale."""
    h, w = grey.shape
    wpt, hpt = w * 72.0 / dpi, h * 72.0 / dpi
    pixels = zlib.compress(np.ascontiguousarray(grey, np.uint8).tobytes(), 9)
    content = f"q {wpt:.4f} 0 0 {hpt:.4f} 0 0 cm /Im0 Do Q".encode()
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {wpt:.4f} {hpt:.4f}] /Resources << /XObject << /Im0 5 0 R >> >> "
        f"/Contents 4 0 R >>".encode(),
        f"<< /Length {len(content)} >>\nstream\n".encode() + content + b"\nendstream",
        f"<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray /BitsPerComponent 8 "
        f"/Interpolate false /Filter /FlateDecode /Length {len(pixels)} >>\nstream\n".encode() + pixels + b"\nendstream",
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objects, 1):
        offsets.append(len(out))
        out += f"{i} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode()
    out += b"".join(f"{o:010d} 00000 n \n".encode() for o in offsets)
    out += f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    return bytes(out)


def _write_bytes(path: Path, data: bytes, owned: OwnedFiles | None = None) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    if owned is not None:
        owned.wrote(path.name, data)


# ---------------------------------------------------------------- the pages
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


def box_size_mm(size: str = "A4", faces: int = 3) -> tuple[float, float, float]:
    """The smallest box (x, y, z extents, mm) the sheets of a generated target fit on (module doc)."""
    w, h = PAPER_MM[size]
    return (w, h if faces == 3 else w, h)


def _claim_out_folder(out: Path, force: bool, faces: int) -> OwnedFiles:
    """Refuse, before any work, a folder that is a file, holds other files (unless ``force``) or
    holds a file of a name ``target`` writes that ``target`` did not write (even with ``force``:
    the user's target.json or face_7.png is theirs). Returns the folder's record of its files."""
    if out.exists() and not out.is_dir():
        raise StereoseedError(f"{out}: is a file; give a folder to write the target into")
    owned = OwnedFiles(out, TARGET_RECORD, "stereoseed target")
    if not out.is_dir():
        return owned
    names = sorted(p.name for p in out.iterdir() if p.name != TARGET_RECORD)
    if not force:
        foreign = [n for n in names if not _OURS.fullmatch(n)]
        if foreign:
            more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
            raise StereoseedError(f"{out}: holds files stereoseed target did not write ({', '.join(foreign[:3])}{more}); "
                                  "give an empty or new folder, or --force to write beside them")
    # the names this run writes, and the stale pages of a run with more faces (removed: only ours)
    owned.refuse_foreign(_written_names(faces) + [n for n in names if _stale_page(n, faces)])
    return owned


def _written_names(faces: int) -> list[str]:
    return [f"face_{k}.{ext}" for k in range(faces) for ext in ("png", "pdf")] + ["assembly.png", "target.json"]


def _stale_page(name: str, faces: int) -> bool:
    return name.startswith("face_") and _OURS.fullmatch(name) is not None and int(name[5:].split(".")[0]) >= faces


def make_target(out_dir: str | os.PathLike, size: str = "A4", faces: int = 3, force: bool = False) -> Path:
    """Write the printable target into ``out_dir``: ``face_<k>.png`` (300 dpi, pHYs),
    ``face_<k>.pdf`` (true scale), ``assembly.png`` and ``target.json``, and the record of what it
    wrote (``.stereoseed-target.json``). A folder holding other files is refused unless ``force``;
    a file of one of those names that this function did not write is refused even then
    (:class:`stereoseed.io.outputs.OwnedFiles`). Returns the path of ``target.json``."""
    if size not in PAPER_MM:
        raise StereoseedError(f"--size {size}: unknown paper size; give one of {', '.join(PAPER_MM)}")
    if faces not in (2, 3):
        raise StereoseedError(f"--faces {faces}: the target has 2 or 3 faces")
    out = Path(out_dir)
    owned = _claim_out_folder(out, force, faces)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("face_*.*"):  # a rerun with fewer faces leaves no stale page behind
        if _stale_page(old.name, faces):  # ours: checked by _claim_out_folder
            old.unlink()
            owned.forget(old.name)
    W, H = _page_px(size)
    face_objs, pages = [], []
    first_id = 0
    for k in range(faces):
        board = _make_board(size, W, H, first_id)
        first_id += board.n_markers
        origin, u, v, label = _face_geometry(k, W, H)
        pages.append(_face_image(board, W, H, k, faces, label))
        _write_bytes(out / f"face_{k}.png", png_with_dpi(pages[-1], DPI), owned)
        _write_bytes(out / f"face_{k}.pdf", pdf_page(pages[-1], DPI), owned)
        face_objs.append(Face(k, out / f"face_{k}.png", origin, u, v, board, (W, H)))
    _write_bytes(out / "assembly.png", png_with_dpi(_assembly_sheet(face_objs, pages, size, W, H), DPI), owned)
    doc = target_json(Target(out / "target.json", face_objs), out,
                      "pixel (u, v) centre of a face image (0, 0 = centre of the top-left pixel) lies at "
                      "origin + u * u_axis + v * v_axis (mm); the printed side faces -(u_axis x v_axis)")
    for entry, label in zip(doc["faces"], ("x = 0", "y = 0", "z = 0, top")):
        entry["plane"] = label
    doc = {"unit": "mm", "paper": size, "dpi": DPI, "box_mm": [round(v, 1) for v in box_size_mm(size, faces)], **doc}
    path = out / "target.json"
    _write_bytes(path, (json.dumps(doc, indent=2, default=jsonable) + "\n").encode("utf-8"), owned)
    owned.save()
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


