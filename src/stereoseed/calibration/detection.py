"""Finding a calibration target (:mod:`stereoseed.calibration.target`) in a photo: ChArUco
corners with their 3D points (mm) and sub-pixel image positions.

Markers are detected once per dictionary and each face's markers (its id range) go to its
:class:`cv2.aruco.CharucoDetector` (corners interpolated from the markers, then refined to
sub-pixel by OpenCV). Each corner is then re-fitted as the saddle point of the image around it
(:func:`_refine_saddles`). Where that fit fails on most of a face's corners, the face is out of
focus (the fit's 5x5 window sees no clean saddle in a blur wider than it): OpenCV's positions are
kept and counted (``Detection.unrefined``), so a blurred view keeps its corners. Where it fails
on a few corners of a sharp face, those corners are dropped and counted (``Detection.dropped``):
there OpenCV's position is pulled by the marker edges beside the corner (up to 1-2 px on an
oblique face, measured on rendered photos).
"""
from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.calibration.target import Target
from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_image

log = logging.getLogger(__name__)

__all__ = ["Detection", "detect_target", "charuco_shift", "MIN_FACE_CORNERS", "MIN_CORNERS"]

# Fewer corners than this on a face: dropped. OpenCV interpolates a ChArUco corner from the
# markers around it, so a face with one to three corners is most often a single marker, easily
# a false one; four is also the least a homography (a flat face's view) needs.
MIN_FACE_CORNERS = 4
# Corners a view needs in all to be used: a pose is 6 unknowns, and a view with fewer corners
# than this adds a pose and little else (it is skipped with this reason).
MIN_CORNERS = 12

_SADDLE_HALF = 2  # the saddle fit's window: (2 * half + 1)^2 pixels
_SADDLE_SIGMA = 1.0  # Gaussian blur before the fit, pixels
_SADDLE_MOVE = 1.5  # a fit that moves further than this (pixels) from OpenCV's corner has failed
# the share of a face's corners the fit fails on above which the face counts as out of focus
# (its failures kept at OpenCV's position): a sharp face fails on isolated corners only (at most
# ~40 % on small oblique renders at 640x480), a defocused one on nearly all (16 of 19 measured)
_BLURRED_SHARE = 0.5
# An X junction is point-symmetric about its centre: mean |patch - patch rotated 180 deg| over
# mean |patch - its mean| at the fitted point is 0.02 on a clean corner (median, 0.19 the worst of
# 336 within 0.06 px of the truth, rendered oblique views), 0.29-0.35 where a marker edge in the
# window let the fit converge 0.1-0.2 px off (corners OpenCV 4.10 interpolates from extra markers):
# above this the fit has failed.
_SADDLE_ASYMMETRY = 0.25
_ys, _xs = np.mgrid[-_SADDLE_HALF:_SADDLE_HALF + 1, -_SADDLE_HALF:_SADDLE_HALF + 1].reshape(2, -1).astype(np.float64)
_SADDLE_FIT = np.linalg.pinv(np.stack([_xs * _xs, _xs * _ys, _ys * _ys, _xs, _ys, np.ones_like(_xs)], axis=1))


@dataclass
class Detection:
    """The target corners found in one image."""
    points3d: np.ndarray  # (N, 3) in the target's frame (mm), the nominal geometry
    pixels: np.ndarray  # (N, 2), (0, 0) the centre of the top-left pixel
    face: np.ndarray  # (N,) face index
    ids: np.ndarray  # (N,) ChArUco corner id within its face
    counts: list[int] = field(default_factory=list)  # corners per face (all faces, found or not)
    unrefined: list[int] = field(default_factory=list)  # per face: corners left at OpenCV's position
    dropped: list[int] = field(default_factory=list)  # per face: corners dropped (the fit failed on a sharp face)
    name: str = "image"
    image_size: tuple[int, int] | None = None  # (width, height)
    refined: np.ndarray | None = None  # (N,) bool: the saddle re-fit succeeded (else OpenCV's corner)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def faces_found(self) -> list[int]:
        return [k for k, n in enumerate(self.counts) if n]

    def problem(self) -> str | None:
        """Why this view cannot be used (None: it can)."""
        if not len(self):
            return "no calibration target found; show the target, well lit and sharp"
        if len(self) < MIN_CORNERS:
            return (f"only {len(self)} target corners found (at least {MIN_CORNERS} needed); come closer so the "
                    "target fills more of the image, sharp and well lit")
        return None

    def summary(self) -> str:
        """'face 0: 46, face 5: 80' and the corners left at OpenCV's position, for messages."""
        text = ", ".join(f"face {k}: {n}" for k, n in enumerate(self.counts) if n) or "no face"
        kept, dropped = sum(self.unrefined), sum(self.dropped)
        if kept:
            text += f" ({kept} left at OpenCV's position: out of focus)"
        if dropped:
            text += f" ({dropped} dropped: no clean saddle point)"
        return text


def _asymmetry(patch: np.ndarray) -> float:
    """How far ``patch`` is from point symmetry about its centre (0: an ideal X junction)."""
    q = patch.astype(np.float64) - patch.mean()
    return float(np.abs(q - q[::-1, ::-1]).mean() / (np.abs(q).mean() + 1e-12))


def _refine_saddles(blurred: np.ndarray, points: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Chessboard corners refined as the saddle point of a quadratic fitted to the blurred image
    around each (Newton steps); (refined (N, 2), ok (N,)). cornerSubPix's gradient window reaches
    the marker borders next to a corner on an oblique face and is pulled by up to ~2 px there; a
    5x5 saddle fit stays on the X junction. A corner that is no saddle, does not converge or
    moves more than ``_SADDLE_MOVE`` px, or whose window is not point-symmetric about the result
    (``_SADDLE_ASYMMETRY``), is not ok, and keeps its starting position."""
    size = (2 * _SADDLE_HALF + 1,) * 2
    out, ok = points.astype(np.float64).copy(), np.zeros(len(points), bool)
    for i, start in enumerate(points.astype(np.float64)):
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
                if _asymmetry(cv2.getRectSubPix(blurred, size, (float(p[0]), float(p[1])))) <= _SADDLE_ASYMMETRY:
                    ok[i] = True
                    out[i] = p
                break
    return out, ok


@functools.cache
def charuco_shift() -> float:
    """What to subtract from the corners ``CharucoDetector.detectBoard`` returns (pixels, both
    axes). OpenCV releases before the fix of its issue #25539 (4.10 among them, the version
    nerfstudio pins) add 0.5 px to each corner after refining it; later ones (5.x) do not. Measured
    once on a board OpenCV draws itself, whose corners lie exactly between pixels, rather than
    guessed from the version number: 0.5 or 0."""
    square, margin = 40, 20
    board = cv2.aruco.CharucoBoard((5, 5), float(square), 30.0,
                                   cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    image = cv2.GaussianBlur(board.generateImage((5 * square + 2 * margin,) * 2, marginSize=margin), (0, 0), 1.0)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(image)
    if ids is None:  # cannot happen with a clean drawn board; assume the fixed behaviour
        return 0.0
    ids = ids.ravel()
    truth = margin - 0.5 + square * np.stack([ids % 4 + 1, ids // 4 + 1], axis=1)
    shift = float(np.median(corners.reshape(-1, 2) - truth))
    log.debug("OpenCV %s's ChArUco corners measured %.3f px off; corrected by %.1f px", cv2.__version__, shift,
              0.5 if shift > 0.25 else 0.0)
    return 0.5 if shift > 0.25 else 0.0  # nearer 0.5 than 0: the old bias


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
    :func:`stereoseed.io.files.read_image`), with their nominal 3D points. ``what`` names the
    image in messages. A face with fewer than ``MIN_FACE_CORNERS`` corners is dropped. The
    detection may be empty or hold one face only: :meth:`Detection.problem` says whether the
    view can be used; which faces a calibration needs is the calibration's to judge."""
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
    pts3d, pix, face_idx, corner_ids, counts, unrefined, fitted, dropped = [], [], [], [], [], [], [], []
    for f in target.faces:
        corners, ids = markers[f.board.dictionary]
        mine = np.flatnonzero((ids >= f.board.first_id) & (ids < f.board.first_id + f.board.n_markers))
        cc = None
        if len(mine) >= 2:
            detector = cv2.aruco.CharucoDetector(f.board.cv_board())
            cc, ci, _, _ = detector.detectBoard(grey, markerCorners=tuple(corners[i] for i in mine),
                                                markerIds=ids[mine].reshape(-1, 1).astype(np.int32))
        n = 0 if cc is None else len(cc)
        if n:
            cc = cc - np.float32(charuco_shift())
        unrefined.append(0)
        dropped.append(0)
        keep = np.ones(n, bool)
        if n:
            refined, ok = _refine_saddles(blurred, cc.reshape(-1, 2))
            if np.mean(~ok) > _BLURRED_SHARE:
                unrefined[-1] = int((~ok).sum())
                log.debug("%s: face %d out of focus: %d corners left at OpenCV's position", what, f.index, unrefined[-1])
            else:
                keep, dropped[-1] = ok, int((~ok).sum())
                if dropped[-1]:
                    log.debug("%s: face %d: %d corners dropped (no clean saddle point)", what, f.index, dropped[-1])
            refined, ok, ci, n = refined[keep], ok[keep], ci.ravel()[keep], int(keep.sum())
        if 0 < n < MIN_FACE_CORNERS:
            log.debug("%s: face %d: only %d corners, dropped", what, f.index, n)
            dropped[-1], unrefined[-1], n = dropped[-1] + n, 0, 0
        counts.append(n)
        if not n:
            continue
        ci = ci.astype(int)
        pts3d.append(f.to_3d(f.board.corner_uv(ci)))
        pix.append(refined)
        fitted.append(ok)
        face_idx.append(np.full(n, f.index))
        corner_ids.append(ci)
    size = (int(grey.shape[1]), int(grey.shape[0]))
    if not pts3d:
        return Detection(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int), counts, unrefined,
                         dropped, what, size, np.zeros(0, bool))
    log.debug("%s: %d target corners (%s per face)", what, sum(counts), counts)
    return Detection(np.concatenate(pts3d), np.concatenate(pix), np.concatenate(face_idx),
                     np.concatenate(corner_ids), counts, unrefined, dropped, what, size, np.concatenate(fitted))
