"""An image brought down to a smaller size and the map of its pixels: pixel (0, 0) is the centre
of the top-left pixel at every size, and an image resized to whole pixels is scaled by its new
width over its width across, its new height over its height down (one scale for both put the
bottom rows of a 3072 x 2048 photo brought to 1000 px a third of a pixel off). The dense stage's
frames (:mod:`stereoseed.dense.frames`) and the quasi-dense registration of large photos use it."""
from __future__ import annotations

import numpy as np

__all__ = ["brought_down", "ratio_of", "to_frame", "from_frame", "frame_matrix"]


def ratio_of(size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """(2,) the ratio of new_size to size, both (width, height): each axis's own scale."""
    return np.array(new_size, np.float64) / np.array(size, np.float64)


def brought_down(image: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The image (H, W[, C]) brought down to a longer side of ``max_side`` pixels (OpenCV's area
    resampling: no aliasing on the way down) and its :func:`ratio_of`; itself and None when it
    fits (or max_side is 0)."""
    import cv2

    h, w = image.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return image, None
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), ratio_of((w, h), size)


def to_frame(xy: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of an image in it resized by ``ratio`` (2,): x' = (x + 0.5) r - 0.5."""
    return (np.asarray(xy, np.float64) + 0.5) * ratio - 0.5


def from_frame(xy: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """:func:`to_frame`'s inverse."""
    return (np.asarray(xy, np.float64) + 0.5) / ratio - 0.5


def frame_matrix(ratio: np.ndarray) -> np.ndarray:
    """:func:`to_frame` as a (3, 3) matrix on homogeneous pixels (a camera P becomes M @ P)."""
    rx, ry = float(ratio[0]), float(ratio[1])
    return np.array([[rx, 0.0, 0.5 * rx - 0.5], [0.0, ry, 0.5 * ry - 0.5], [0.0, 0.0, 1.0]])
