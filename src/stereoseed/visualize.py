"""Drawings of the stages' results: the propagation's colour-coded disparity (paper Fig. 10d)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import StereoseedError
from .propagation import PropagationResult

__all__ = ["disparity_image", "save_propagation_png"]


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(img1)
    if img.dtype != np.uint8:
        img = np.clip(np.rint(np.asarray(img, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    disp = disparity_image(result, img.shape)
    if not cv2.imwrite(str(path), np.hstack([img, disp])):
        raise StereoseedError(f"could not write {path}")
    return path
