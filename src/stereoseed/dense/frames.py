"""The dense stage's image frames: the propagation may run on images brought down to a chosen
resolution (``DenseConfig.resolution``, ``--dense-resolution``); the cameras, the seeds and the
pixel footprint follow them."""
from __future__ import annotations

from typing import Any

import numpy as np

from stereoseed.geometry.resampling import frame_matrix, ratio_of

__all__ = ["dense_scale", "scaling", "frame_map", "dense_frames", "budgeted_resolution", "resized"]


def dense_scale(size: tuple[int, int], resolution: int) -> float:
    """The factor (<= 1) an image of size (width, height) is resized by for the propagation:
    its longer side brought down to ``resolution`` pixels (0: kept)."""
    return min(1.0, resolution / max(size)) if resolution else 1.0


def scaling(scale: float, scale_y: float | None = None) -> np.ndarray:
    """The pixel map (3, 3) of an image resized by ``scale`` (by ``scale_y`` down when given),
    :func:`~stereoseed.geometry.resampling.frame_matrix`."""
    return frame_matrix((scale, scale if scale_y is None else scale_y))


def frame_map(size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """The pixel map (3, 3) of an image of size (width, height) resized to new_size, each axis
    by its own ratio (:mod:`stereoseed.geometry.resampling`)."""
    return frame_matrix(ratio_of(size, new_size))


def dense_frames(views: list[Any], resolution: int) -> tuple[list[float], list[np.ndarray], list[tuple[int, int]]]:
    """Per view (:class:`~stereoseed.scene.view.View`): the propagation's scale
    (DenseConfig.resolution), its camera and image size in that frame (a view without a camera:
    the identity's, never paired)."""
    scales, cameras, sizes = [], [], []
    for v in views:
        size = v.image_size or (1, 1)
        s = dense_scale(size, resolution)
        new_size = (int(round(size[0] * s)), int(round(size[1] * s))) if s < 1 else tuple(size)
        scales.append(s)
        cameras.append(frame_map(size, new_size) @ v.P if v.P is not None else np.eye(3, 4))
        sizes.append(new_size)
    return scales, cameras, sizes


def budgeted_resolution(views: list[Any], pairs: list[tuple[int, int]], resolution: int, max_megapixels: float) -> int:
    """The propagation's resolution (a longer side in pixels, 0: as given) that keeps the pairs'
    first images within ``max_megapixels`` in all (0: no limit): ``resolution`` when they fit,
    else the largest longer side at which they do (every image brought down alike). The fusion
    holds a depth map and the points of every pair, so its memory goes with that sum."""
    def megapixels(side: int) -> float:
        total = 0.0
        for a, _ in pairs:
            size = views[a].image_size or (1, 1)
            s = dense_scale(size, side)
            total += round(size[0] * s) * round(size[1] * s) / 1e6
        return total

    if not max_megapixels or not pairs or megapixels(resolution) <= max_megapixels:
        return resolution
    low, high = 1, max(max(views[a].image_size or (1, 1)) for a, _ in pairs)
    if resolution:
        high = min(high, resolution)
    while low < high:  # the largest side within the budget (the pixels grow with the side)
        mid = (low + high + 1) // 2
        if megapixels(mid) <= max_megapixels:
            low = mid
        else:
            high = mid - 1
    return low


def resized(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The image brought to size (width, height); itself when it has that size already."""
    import cv2

    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)  # area: no aliasing on the way down
