"""Interest points (Harris + sub-pixel refinement) and ZNCC patch descriptors.

Paper §4.1 step 2 and §4.2: Harris points in every image, matched by normalised cross-correlation.
The descriptor of a point is simply its grey-level patch, made zero-mean and unit-norm, so that
the dot product of two descriptors *is* their ZNCC score and all scores between two images come
from one matrix product (see :mod:`stereoseed.matching`).

Conventions: images are (H, W) float32 grey levels in [0, 1]; points are (N, 2) float64
``(x, y)`` pixels with (0, 0) the centre of the top-left pixel (see :mod:`stereoseed.camera`).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from .config import FeatureConfig, MatchingConfig
from .errors import StereoseedError

__all__ = ["Features", "to_gray", "detect_corners", "describe", "extract_features"]

# A patch whose grey-level standard deviation is below this (in [0, 1] units, ~0.25 grey level
# of an 8-bit image) has no usable signal: its ZNCC would be driven by quantisation alone.
DEFAULT_MIN_PATCH_STD = 1e-3


@dataclass(frozen=True)
class Features:
    """Interest points of one image with their ZNCC descriptors.

    points: (N, 2) float64 sub-pixel positions ``(x, y)``, strongest Harris response first.
    desc: (N, P*P) float32 zero-mean unit-norm patches (rows of zeros where ``valid`` is False).
    valid: (N,) bool, False for points whose patch leaves the image or is flat.
    response: (N,) float64 Harris response at the (integer) detection position.
    image_shape: (H, W) of the grey image the points were found in.
    """

    points: np.ndarray
    desc: np.ndarray
    valid: np.ndarray
    response: np.ndarray
    image_shape: tuple[int, int]

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def patch_size(self) -> int:
        """Side P of the square descriptor patch."""
        return int(round(np.sqrt(self.desc.shape[1])))


def to_gray(image: np.ndarray) -> np.ndarray:
    """Convert an image to (H, W) float32 grey levels in [0, 1].

    image: (H, W) or (H, W, 1) grey, (H, W, 3) BGR or (H, W, 4) BGRA (OpenCV channel order);
    dtype uint8 (divided by 255), uint16 (divided by 65535), bool, or float. Float images are taken
    to be in [0, 1]; a float image whose maximum exceeds 1 is taken to be in [0, 255]. NaN/inf
    become 0 and the result is clipped to [0, 1].
    Raises StereoseedError for any other shape.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise StereoseedError(
            f"image of shape {img.shape} is not a grey (H, W), BGR (H, W, 3) or BGRA (H, W, 4) image"
        )
    if img.dtype == np.uint8:
        gray = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        gray = img.astype(np.float32) / 65535.0
    elif img.dtype == bool or np.issubdtype(img.dtype, np.number):
        gray = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if gray.size and gray.max() > 1.0:
            gray /= 255.0
    else:
        raise StereoseedError(f"image dtype {img.dtype} is not numeric")
    if gray.ndim == 3:
        if gray.size == 0:
            gray = gray[:, :, 0]
        else:
            code = cv2.COLOR_BGR2GRAY if gray.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            gray = cv2.cvtColor(np.ascontiguousarray(gray), code)
    return np.ascontiguousarray(np.clip(gray, 0.0, 1.0), dtype=np.float32)


def _empty_points(reason: str) -> tuple[np.ndarray, np.ndarray]:
    warnings.warn(f"no interest points: {reason}", RuntimeWarning, stacklevel=3)
    return np.zeros((0, 2), np.float64), np.zeros(0, np.float64)


def detect_corners_with_response(
    gray: np.ndarray, config: FeatureConfig = FeatureConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Harris corners with their responses; see :func:`detect_corners`.

    Returns points (N, 2) float64 and response (N,) float64, strongest first.
    """
    gray = np.asarray(gray)
    if gray.ndim != 2:
        raise StereoseedError(f"detect_corners needs a (H, W) grey image, got shape {gray.shape}")
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    h, w = gray.shape
    b = int(config.border)
    if h <= 2 * b + 2 or w <= 2 * b + 2:
        return _empty_points(f"image {w}x{h} is too small for a border of {b} px")
    if not np.all(np.isfinite(gray)) or float(gray.max() - gray.min()) <= 0.0:
        return _empty_points("the image is flat or not finite")

    # The mask keeps detections away from the edge: their patch must fit in the image.
    mask = np.zeros((h, w), np.uint8)
    mask[b : h - b, b : w - b] = 255
    # goodFeaturesToTrack = Harris response + 3x3 local maxima + relative quality floor + greedy
    # min-distance suppression in order of decreasing response + max count, all in C++.
    corners, quality = cv2.goodFeaturesToTrackWithQuality(
        gray,
        maxCorners=int(config.max_corners),
        qualityLevel=float(config.quality_level),
        minDistance=float(config.min_distance),
        mask=mask,
        blockSize=int(config.block_size),
        gradientSize=int(config.aperture),
        useHarrisDetector=True,
        k=float(config.harris_k),
    )
    if corners is None or len(corners) == 0:
        return _empty_points("no Harris maximum above the quality floor")
    corners = corners.reshape(-1, 1, 2).astype(np.float32)
    response = np.asarray(quality, np.float64).reshape(-1)
    # Harris responses are positive at corners; a non-positive best response means only edges.
    keep = response > 0
    corners, response = corners[keep], response[keep]
    if len(corners) == 0:
        return _empty_points("no positive Harris response")

    win = int(config.subpixel_window)
    if win > 0:
        start = corners[:, 0, :].astype(np.float64)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 1e-3)
        cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), criteria)
        pts = corners[:, 0, :].astype(np.float64)
        # cornerSubPix may wander off when the window holds no clear corner (e.g. an edge):
        # a refinement that leaves the search window is not a refinement, keep the detection.
        moved = np.abs(pts - start).max(axis=1) > win
        bad = moved | ~np.all(np.isfinite(pts), axis=1)
        pts[bad] = start[bad]
    else:
        pts = corners[:, 0, :].astype(np.float64)

    inside = (
        (pts[:, 0] >= b) & (pts[:, 0] <= w - 1 - b) & (pts[:, 1] >= b) & (pts[:, 1] <= h - 1 - b)
    )
    pts, response = pts[inside], response[inside]
    # goodFeaturesToTrack already returns strongest first; a stable sort makes it a guarantee.
    order = np.argsort(-response, kind="stable")
    return pts[order], response[order]


def detect_corners(gray: np.ndarray, config: FeatureConfig = FeatureConfig()) -> np.ndarray:
    """Harris interest points with sub-pixel positions.

    gray: (H, W) float32 in [0, 1] (see :func:`to_gray`).
    Returns (N, 2) float64 ``(x, y)``, N <= ``config.max_corners``, sorted by Harris response
    (strongest first), pairwise at least ``config.min_distance`` apart at detection, at least
    ``config.border`` px from the image edge. Refined with ``cv2.cornerSubPix`` over a
    ``(2 * subpixel_window + 1)``² window. Empty, tiny or flat images give a (0, 2) array and a
    RuntimeWarning.
    """
    return detect_corners_with_response(gray, config)[0]


def _bilinear_patches(gray: np.ndarray, points: np.ndarray, patch_size: int) -> np.ndarray:
    """Sample (N, P*P) float32 patches centred on sub-pixel points by bilinear interpolation.

    Samples outside the image are clamped to the edge (the caller marks those patches invalid).
    """
    h, w = gray.shape
    r = patch_size // 2
    d = np.arange(-r, r + 1, dtype=np.float64)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    xs = points[:, 0:1] + dx.reshape(1, -1)  # (N, P*P), row-major patch order
    ys = points[:, 1:2] + dy.reshape(1, -1)
    x0 = np.floor(xs)
    y0 = np.floor(ys)
    fx = (xs - x0).astype(np.float32)
    fy = (ys - y0).astype(np.float32)
    x0 = np.clip(x0.astype(np.int64), 0, w - 1)
    y0 = np.clip(y0.astype(np.int64), 0, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    flat = gray.reshape(-1)
    top = flat[y0 * w + x0] * (1 - fx) + flat[y0 * w + x1] * fx
    bottom = flat[y1 * w + x0] * (1 - fx) + flat[y1 * w + x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def describe(
    gray: np.ndarray,
    points: np.ndarray,
    patch_size: int = MatchingConfig().patch_size,
    *,
    min_std: float = DEFAULT_MIN_PATCH_STD,
) -> tuple[np.ndarray, np.ndarray]:
    """ZNCC descriptors: zero-mean, unit-norm grey-level patches at sub-pixel positions.

    gray: (H, W) float32 in [0, 1]; points: (N, 2) float64 ``(x, y)``; patch_size: odd P >= 3.
    Returns desc (N, P*P) float32 with ``desc[i] @ desc[j]`` the ZNCC of the two patches, and
    valid (N,) bool: False (and a zero row) when the patch does not fit in the image, a
    coordinate is not finite, or the patch standard deviation is below ``min_std``.
    """
    gray = np.asarray(gray)
    if gray.ndim != 2:
        raise StereoseedError(f"describe needs a (H, W) grey image, got shape {gray.shape}")
    if int(patch_size) != patch_size or patch_size < 3 or patch_size % 2 == 0:
        raise StereoseedError(f"patch_size must be an odd integer >= 3, got {patch_size}")
    patch_size = int(patch_size)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = pts.shape[0]
    desc = np.zeros((n, patch_size * patch_size), np.float32)
    h, w = gray.shape
    r = patch_size // 2
    finite = np.all(np.isfinite(pts), axis=1)
    inside = finite.copy()
    inside[finite] = (
        (pts[finite, 0] >= r)
        & (pts[finite, 0] <= w - 1 - r)
        & (pts[finite, 1] >= r)
        & (pts[finite, 1] <= h - 1 - r)
    )
    if n == 0 or not inside.any():
        return desc, np.zeros(n, bool)

    patches = _bilinear_patches(np.ascontiguousarray(gray, np.float32), pts[inside], patch_size)
    patches -= patches.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(patches, axis=1)
    # norm / sqrt(P*P) is the patch standard deviation.
    ok = norm > min_std * patch_size
    patches[ok] /= norm[ok, None]
    patches[~ok] = 0.0
    desc[inside] = patches
    valid = inside.copy()
    valid[inside] = ok
    return desc, valid


def extract_features(
    image: np.ndarray,
    config: FeatureConfig = FeatureConfig(),
    *,
    patch_size: int = MatchingConfig().patch_size,
) -> Features:
    """Detect and describe the interest points of one image.

    image: anything :func:`to_gray` accepts. ``patch_size`` should be the matching
    configuration's (``MatchingConfig.patch_size``).
    """
    gray = to_gray(image)
    points, response = detect_corners_with_response(gray, config)
    desc, valid = describe(gray, points, patch_size)
    return Features(points, desc, valid, response, (int(gray.shape[0]), int(gray.shape[1])))
