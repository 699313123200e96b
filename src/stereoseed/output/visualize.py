"""Drawings of intermediate results, for people: matches between two images side by side
(paper Fig. 10b) and the propagation's colour-coded disparity (paper Fig. 10d)."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from stereoseed.io.files import write_image
from stereoseed.features.harris import Features
from stereoseed.matching.containers import Matches
from stereoseed.matching.propagation.core import PropagationResult

__all__ = ["draw_matches", "spread_matches", "disparity_image", "save_propagation_png", "draw_calibration_check"]


def _to_bgr_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        f = np.nan_to_num(img.astype(np.float64))
        scale = 255.0 if f.size and f.max() <= 1.0 else 1.0  # [0, 1] floats or 0..255 values
        img = np.clip(f * scale, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def draw_matches(
    img1: np.ndarray,
    kp1: Features | np.ndarray,
    img2: np.ndarray,
    kp2: Features | np.ndarray,
    matches: Matches,
    path: str | Path | None = None,
    *,
    max_lines: int | None = None,
    thickness: int = 1,
) -> np.ndarray:
    """Side-by-side image with a line per match (paper Fig. 10b), written as PNG if ``path``.

    img1, img2: grey or BGR images (uint8 or float in [0, 1]); kp1, kp2: Features or (N, 2).
    Line colour goes from red (lowest ZNCC) to green (highest). ``max_lines`` keeps the best
    (:func:`spread_matches` picks a few spread over the image instead). ``thickness``: of the
    lines and circles in pixels (a canvas shown scaled down needs more than 1).
    Returns the (max(H1, H2), W1 + W2, 3) uint8 BGR canvas.
    """
    a, b = _to_bgr_u8(img1), _to_bgr_u8(img2)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] :] = b
    m = matches.sorted_by_score()
    if max_lines is not None:
        m = m.subset(slice(0, max_lines))
    if len(m):
        x1, x2 = m.points(kp1, kp2)
        x2 = x2 + np.array([a.shape[1], 0.0])
        lo, hi = float(m.score.min()), float(m.score.max())
        t = (m.score - lo) / (hi - lo) if hi > lo else np.ones(len(m))
        shift = 4  # draw at 1/16 px so sub-pixel positions are honoured
        p1 = np.round(x1 * (1 << shift)).astype(np.int64)
        p2 = np.round(x2 * (1 << shift)).astype(np.int64)
        # Draw the weakest first so the best matches stay on top.
        for k in np.argsort(m.score):
            colour = (0, int(255 * t[k]), int(255 * (1 - t[k])))
            q1 = (int(p1[k, 0]), int(p1[k, 1]))
            q2 = (int(p2[k, 0]), int(p2[k, 1]))
            cv2.line(canvas, q1, q2, colour, thickness, cv2.LINE_AA, shift)
            cv2.circle(canvas, q1, (1 + thickness) << shift, colour, thickness, cv2.LINE_AA, shift)
            cv2.circle(canvas, q2, (1 + thickness) << shift, colour, thickness, cv2.LINE_AA, shift)
    if path is not None:
        write_image(path, canvas)
    return canvas


def spread_matches(matches: Matches, kp1: Features | np.ndarray, image_size: tuple[int, int], limit: int) -> np.ndarray:
    """Positions (sorted) of at most ``limit`` of ``matches`` spread over image 1 (``image_size``:
    width, height): the image is cut into about ``limit`` cells, and the matches are taken
    round by round, in each round the best ZNCC not yet taken of every cell, best cells first; so
    a drawing of them shows where the matches are, not a band of lines where they crowd."""
    n = len(matches)
    if n <= limit:
        return np.arange(n)
    w, h = image_size
    cols = max(1, round(math.sqrt(limit * w / max(h, 1))))
    rows = max(1, math.ceil(limit / cols))
    x1 = np.asarray(kp1.points if isinstance(kp1, Features) else kp1, np.float64)[matches.idx1]
    cell = (np.clip((x1[:, 1] * rows / h).astype(np.int64), 0, rows - 1) * cols
            + np.clip((x1[:, 0] * cols / w).astype(np.int64), 0, cols - 1))
    by_score = np.lexsort((-matches.score, cell))  # cell by cell, best first
    sorted_cells = cell[by_score]
    rank = np.empty(n, np.int64)
    starts = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank[by_score] = np.arange(n) - starts  # the match's place in its cell
    order = np.lexsort((-matches.score, rank))
    return np.sort(order[:limit])


def disparity_image(result: PropagationResult, shape: tuple[int, ...]) -> np.ndarray:
    """Colour-coded disparity of every matched pixel of image 1 (paper Fig. 10d).

    The displacement x2 - x1 of each match is projected on the dominant displacement direction
    (the principal axis of all displacements: the x-axis for a rectified pair), so that an
    unrectified pair still gets one scalar "disparity"; its 2nd-98th percentile range is mapped
    to the JET colour map. Unmatched pixels are black.

    result: a :class:`PropagationResult`; shape: (H1, W1) or (H1, W1, C) of image 1.
    Returns (H1, W1, 3) uint8 BGR.
    """
    H, W = int(shape[0]), int(shape[1])
    out = np.zeros((H, W, 3), dtype=np.uint8)
    if result.n_matches == 0:
        return out
    m = result.matches
    disp = m[:, 2:4] - m[:, 0:2]
    centred = disp - disp.mean(axis=0)
    if disp.shape[0] >= 2 and np.any(centred):
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        axis = vt[0]
    else:
        axis = np.array([1.0, 0.0])
    if axis[np.argmax(np.abs(axis))] < 0:  # deterministic sign: larger along +x/+y is "more"
        axis = -axis
    val = disp @ axis
    lo, hi = np.percentile(val, [2.0, 98.0])
    norm = np.clip((val - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    grey = np.rint(norm * 255.0).astype(np.uint8).reshape(-1, 1)
    colours = cv2.applyColorMap(grey, cv2.COLORMAP_JET).reshape(-1, 3)
    xi = m[:, 0].astype(np.int64)
    yi = m[:, 1].astype(np.int64)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    out[yi[inside], xi[inside]] = colours[inside]
    return out


def save_propagation_png(img1: np.ndarray, result: PropagationResult, path: str | Path) -> Path:
    """Write image 1 (left) beside its colour-coded disparity (right) as a PNG.

    img1: (H, W) grey float in [0, 1] / uint8, or (H, W, 3) BGR uint8. Returns the path written.
    """
    img = _to_bgr_u8(img1)
    return write_image(path, np.hstack([img, disparity_image(result, img.shape)]))


def draw_calibration_check(image: np.ndarray, detected: np.ndarray, reprojected: np.ndarray,
                           path: str | Path | None = None) -> np.ndarray:
    """The calibration image with each detected target corner (green circle) and where the
    calibrated camera and lens put it (red cross), so a user sees that it worked.
    detected, reprojected: (N, 2) pixels. Returns the BGR canvas (written as PNG if ``path``)."""
    canvas = _to_bgr_u8(image).copy()
    shift = 4  # circles drawn at 1/16 px so sub-pixel positions are honoured
    for (x, y), (u, v) in zip(np.asarray(detected), np.asarray(reprojected)):
        cv2.circle(canvas, (int(round(x * (1 << shift))), int(round(y * (1 << shift)))), 4 << shift, (0, 200, 0), 1,
                   cv2.LINE_AA, shift)
        cv2.drawMarker(canvas, (int(round(u)), int(round(v))), (0, 0, 255), cv2.MARKER_CROSS, 6, 1, cv2.LINE_AA)
    if path is not None:
        write_image(path, canvas)
    return canvas
