"""The dense stage's image frames: the propagation may run on images brought down to a chosen
resolution (``DenseConfig.resolution``, ``--dense-resolution``); the cameras, the seeds and the
pixel footprint follow them."""
from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["dense_scale", "scaling", "dense_frames", "resized"]


def dense_scale(size: tuple[int, int], resolution: int) -> float:
    """The factor (<= 1) an image of size (width, height) is resized by for the propagation:
    its longer side brought down to ``resolution`` pixels (0: kept)."""
    return min(1.0, resolution / max(size)) if resolution else 1.0


def scaling(scale: float) -> np.ndarray:
    """The pixel map (3, 3) of an image resized by ``scale``, pixel (0, 0) the centre of the
    top-left pixel in both: x' = (x + 0.5) scale - 0.5."""
    shift = 0.5 * scale - 0.5
    return np.array([[scale, 0.0, shift], [0.0, scale, shift], [0.0, 0.0, 1.0]])


def dense_frames(views: list[Any], resolution: int) -> tuple[list[float], list[np.ndarray], list[tuple[int, int]]]:
    """Per view (:class:`~stereoseed.scene.view.View`): the propagation's scale
    (DenseConfig.resolution), its camera and image size in that frame (a view without a camera:
    the identity's, never paired)."""
    scales, cameras, sizes = [], [], []
    for v in views:
        size = v.image_size or (1, 1)
        s = dense_scale(size, resolution)
        scales.append(s)
        cameras.append(scaling(s) @ v.P if v.P is not None else np.eye(3, 4))
        sizes.append((int(round(size[0] * s)), int(round(size[1] * s))) if s < 1 else tuple(size))
    return scales, cameras, sizes


def resized(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The image brought to size (width, height); itself when it has that size already."""
    import cv2

    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)  # area: no aliasing on the way down
