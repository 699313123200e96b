"""Interest points (Harris + sub-pixel refinement) and ZNCC patch descriptors.

Paper §4.1 step 2 and §4.2: Harris points in every image, matched by normalised cross-correlation.
The descriptor of a point is simply its grey-level patch, made zero-mean and unit-norm, so that
the dot product of two descriptors *is* their ZNCC score and all scores between two images come
from one matrix product (see :mod:`stereoseed.matching`).

Conventions: images are (H, W) float32 grey levels in [0, 1]; points are (N, 2) float64
``(x, y)`` pixels with (0, 0) the centre of the top-left pixel (see :mod:`stereoseed.geometry.projection`).

The grey conversion (:func:`to_gray`) and :func:`sample_bilinear` live in :mod:`stereoseed.features.image`
and are re-exported here; the junctions' edge intersection is :mod:`stereoseed.features.edge_corners`.
Why the sub-pixel refinement is built the way it is, with figures: ``docs/features.md``.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit

from stereoseed.features.config import FeatureConfig

from stereoseed.matching.config import MatchingConfig
from stereoseed.features.edge_corners import corners_on_edges
from stereoseed.errors import StereoseedError
from stereoseed.features.image import sample_bilinear, to_gray
from stereoseed.geometry.neighbours import repeats_earlier

_log = logging.getLogger(__name__)

__all__ = [
    "Features",
    "to_gray",
    "detect_corners",
    "detect_corners_with_response",
    "describe",
    "describe_scaled",
    "extract_features",
    "sample_bilinear",
    "DEFAULT_MIN_PATCH_STD",
]

# A patch whose grey-level standard deviation is below this (in [0, 1] units, ~0.25 grey level
# of an 8-bit image) has no usable signal: its ZNCC would be driven by quantisation alone.
DEFAULT_MIN_PATCH_STD = 1e-3
_REMAP_ROWS = 16384
_SAME_POINT_PX = 0.5  # interest points closer than this stand for one image point


@dataclass(frozen=True)
class Features:
    """Interest points of one image with their ZNCC descriptors.

    points: (N, 2) float64 sub-pixel positions ``(x, y)``, strongest Harris response first.
    desc: (N, P*P) float32 zero-mean unit-norm patches (rows of zeros where ``valid`` is False).
    valid: (N,) bool, False for points whose patch leaves the image or is flat.
    response: (N,) float64 Harris response at the (integer) detection position.
    image_shape: (H, W) of the grey image the points were found in.
    gray: (H, W) float32 grey image in [0, 1], kept for the sub-pixel alignment of matches
        (:func:`stereoseed.matching.alignment.align_matches`); None if not available.
    """

    points: np.ndarray
    desc: np.ndarray
    valid: np.ndarray
    response: np.ndarray
    image_shape: tuple[int, int]
    gray: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def patch_size(self) -> int:
        """Side P of the square descriptor patch."""
        return int(round(np.sqrt(self.desc.shape[1])))


def _empty_points(reason: str) -> tuple[np.ndarray, np.ndarray]:
    # not an error: the caller gets empty arrays and decides (an image may just be blank)
    _log.info("no interest points: %s", reason)
    return np.zeros((0, 2), np.float64), np.zeros(0, np.float64)


def detect_corners_with_response(
    gray: np.ndarray,
    config: FeatureConfig = FeatureConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Harris corners with their responses; see :func:`detect_corners`.

    Returns points (N, 2) float64 and response (N,) float64, strongest first.
    """
    gray = np.asarray(gray)
    if gray.ndim != 2:
        raise StereoseedError(f"detect_corners needs a (H, W) grey image, got shape {gray.shape}")
    gray = np.ascontiguousarray(gray, dtype=np.float32)
    h, w = gray.shape
    # At least one pixel: the quadratic peak fit reads the 3x3 neighbourhood of each maximum.
    b = max(int(config.border), 1)
    if h <= 2 * b + 2 or w <= 2 * b + 2:
        return _empty_points(f"image {w}x{h} is too small for a border of {b} px")
    if not np.all(np.isfinite(gray)) or float(gray.max() - gray.min()) <= 0.0:
        return _empty_points("the image is flat or not finite")

    # The mask keeps detections away from the edge: their patch must fit in the image.
    mask = np.zeros((h, w), np.uint8)
    mask[b : h - b, b : w - b] = 255
    # goodFeaturesToTrack = Harris response + 3x3 local maxima + relative quality floor + greedy
    # min-distance suppression in order of decreasing response + max count, all in C++.
    corners = cv2.goodFeaturesToTrack(
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
    corners = corners.reshape(-1, 1, 2)
    xi = np.rint(corners[:, 0, 0]).astype(np.int64)
    yi = np.rint(corners[:, 0, 1]).astype(np.int64)
    harris = cv2.cornerHarris(
        gray, int(config.block_size), int(config.aperture), float(config.harris_k)
    )
    response = harris[yi, xi].astype(np.float64)
    pts = _refine_subpixel(gray, harris, xi, yi, int(config.subpixel_window),
                           float(config.junction_tol), bool(config.edge_corners))

    inside = (
        (pts[:, 0] >= b) & (pts[:, 0] <= w - 1 - b) & (pts[:, 1] >= b) & (pts[:, 1] <= h - 1 - b)
    )
    # Harris responses are positive at corners; a non-positive response means an edge or flat.
    keep = inside & (response > 0)
    pts, response = pts[keep], response[keep]
    if len(pts) == 0:
        return _empty_points("no positive Harris response")
    # goodFeaturesToTrack already returns strongest first; a stable sort makes it a guarantee.
    order = np.argsort(-response, kind="stable")
    pts, response = pts[order], response[order]
    # Two Harris maxima of one corner can refine to the same position (both arms of an L corner
    # peak): one interest point per position, the strongest.
    weaker = repeats_earlier(pts, _SAME_POINT_PX)  # within the distance of a stronger one
    if weaker.any():
        pts, response = pts[~weaker], response[~weaker]
    return pts, response


def _quadratic_peak(harris: np.ndarray, xi: np.ndarray, yi: np.ndarray) -> np.ndarray:
    """Sub-pixel maxima of the Harris response: (N, 2) float64 from integer maxima (N,), (N,).

    Fits a 2-D quadratic to the 3x3 neighbourhood (central differences). Where the fit is not a
    maximum within one pixel, falls back to independent 1-D parabolas clipped to +-0.5 px.
    The maxima must be at least one pixel inside the image.
    """
    r = harris.astype(np.float64)
    c = r[yi, xi]
    left, right = r[yi, xi - 1], r[yi, xi + 1]
    up, down = r[yi - 1, xi], r[yi + 1, xi]
    gx, gy = 0.5 * (right - left), 0.5 * (down - up)
    hxx, hyy = right + left - 2.0 * c, down + up - 2.0 * c
    hxy = 0.25 * (r[yi + 1, xi + 1] - r[yi + 1, xi - 1] - r[yi - 1, xi + 1] + r[yi - 1, xi - 1])
    det = hxx * hyy - hxy**2
    with np.errstate(divide="ignore", invalid="ignore"):
        ox = -(hyy * gx - hxy * gy) / det
        oy = -(hxx * gy - hxy * gx) / det
        ox1 = np.clip(np.nan_to_num(-gx / hxx), -0.5, 0.5)
        oy1 = np.clip(np.nan_to_num(-gy / hyy), -0.5, 0.5)
    # A maximum needs a negative-definite Hessian; beyond one pixel the fit is extrapolating.
    good = (det > 0) & (hxx < 0) & (np.abs(ox) <= 1.0) & (np.abs(oy) <= 1.0)
    ox = np.where(good, ox, ox1)
    oy = np.where(good, oy, oy1)
    return np.stack([xi + ox, yi + oy], axis=1)


@njit(cache=True, nogil=True, inline="always")
def _eightfold_sum(a: np.ndarray, n: int) -> float:
    """Sum of a[:n] float64 as NumPy sums up to 128 values (eight running sums combined as a
    tree, then the rest in order), so that the default windows' residuals (11 x 11, 7 x 7) are
    NumPy's bit for bit and the interest points did not move when the kernel replaced NumPy. Not
    recursive (Numba's cache cannot hold a recursive function): a window above 128 pixels is
    summed the same way, equal to NumPy's sum up to rounding."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - n % 8:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def _junction_residual_kernel(gx, gy, q, win, strong_fraction, out):
    """:func:`_junction_residual` of each point of q (N, 2) into out (N,): the products in
    float32 as the gradients are, the sums in float64."""
    h, w = gx.shape
    k = (2 * win + 1) ** 2
    g2 = np.empty(k, np.float32)
    along = np.empty(k)  # float32 products, widened exactly
    full = np.empty(k)
    for i in range(q.shape[0]):
        qx = min(max(np.int64(np.rint(q[i, 0])), win), w - 1 - win)
        qy = min(max(np.int64(np.rint(q[i, 1])), win), h - 1 - win)
        n = 0
        strongest = np.float32(0.0)
        for dy in range(-win, win + 1):
            for dx in range(-win, win + 1):
                g_x, g_y = gx[qy + dy, qx + dx], gy[qy + dy, qx + dx]
                vx, vy = np.float32(q[i, 0] - qx - dx), np.float32(q[i, 1] - qy - dy)
                g2[n] = g_x * g_x + g_y * g_y
                dot = g_x * vx + g_y * vy
                along[n] = dot * dot
                full[n] = g2[n] * (vx * vx + vy * vy)
                strongest = max(strongest, g2[n])
                n += 1
        if strong_fraction > 0.0:
            weak_below = np.float32(strong_fraction ** 2) * strongest
            for j in range(k):
                if g2[j] < weak_below:
                    along[j] = 0.0
                    full[j] = 0.0
        num, den = _eightfold_sum(along, k), _eightfold_sum(full, k)
        out[i] = num / max(den, 1e-300) if den > 0 else 1.0


def _junction_residual(gx: np.ndarray, gy: np.ndarray, q: np.ndarray, win: int,
                       strong_fraction: float = 0.0) -> np.ndarray:
    """How badly the cornerSubPix model fits at q: (N, 2) -> (N,) float64 in [0, 1].

    gx, gy: (H, W) float32 image gradients. Returns
    sum_p (g_p . (q - p))^2 / sum_p |g_p|^2 |q - p|^2 over the (2 win + 1)^2 pixels p around
    round(q) (kept win px inside the image): 0 when every gradient g_p is orthogonal to q - p (an
    ideal junction at q). strong_fraction > 0 keeps only the pixels whose gradient is at least
    that fraction of the window's strongest: the residual of the high-contrast edges alone.
    """
    out = np.empty(len(q))
    _junction_residual_kernel(np.ascontiguousarray(gx, np.float32), np.ascontiguousarray(gy, np.float32),
                              np.ascontiguousarray(q, np.float64).reshape(-1, 2), int(win), float(strong_fraction),
                              out)
    return out


def _is_junction(gx: np.ndarray, gy: np.ndarray, q: np.ndarray, win: int, tol: float) -> np.ndarray:
    """Where cornerSubPix's position q (N, 2) can be trusted: (N,) bool.

    Either the whole window fits the junction model (residual < tol), or a high-contrast
    junction on a textured surface (a dark square's corner on a textured face): the window as a
    whole fits loosely (< 2 tol) and its strong edges alone (gradients >= half the window's
    strongest) fit tightly (< tol / 2): this admits a dark square's corner on a textured face
    without admitting texture (docs/features.md).
    """
    res = _junction_residual(gx, gy, q, win)
    ok = res < tol
    loose = ~ok & (res < 2.0 * tol)
    if np.any(loose):
        ok[loose] = _junction_residual(gx, gy, q[loose], win, strong_fraction=0.5) < 0.5 * tol
    return ok


def _refine_subpixel(
    gray: np.ndarray,
    harris: np.ndarray,
    xi: np.ndarray,
    yi: np.ndarray,
    win: int,
    junction_tol: float,
    edge_corners: bool = True,
) -> np.ndarray:
    """Sub-pixel positions (N, 2) float64 of integer Harris maxima (xi, yi).

    Textured blobs and junctions need different refinements (docs/features.md): every point gets
    the quadratic Harris peak; cv2.cornerSubPix (window (2 win + 1)^2, started from the peak)
    replaces it where the junction model fits (:func:`_is_junction`) and the refinement stayed
    inside its window; where it does not, a window half as wide is tried the same way. With
    ``edge_corners`` a junction then moves to the intersection of its two edges where both are
    found and straight (:func:`stereoseed.features.edge_corners.corners_on_edges`).
    """
    peak = _quadratic_peak(harris, xi, yi)
    if win <= 0 or len(peak) == 0:
        return peak
    h, w = gray.shape
    if h < 2 * win + 5 or w < 2 * win + 5:  # cv2.cornerSubPix's own requirement
        return peak
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)

    refined = peak.copy()
    ok = np.zeros(len(peak), bool)
    # a square's corner on a textured face often fails the model in the full window (the texture
    # around it) but holds in a smaller one
    smaller = (win + 1) // 2
    for size in (win, smaller) if 2 <= smaller < win else (win,):
        rest = np.flatnonzero(~ok)
        if len(rest) == 0:
            break
        refined[rest], ok[rest] = _junction_refinement(gray, gx, gy, peak[rest], size, junction_tol)
    if edge_corners and ok.any():
        junctions = np.flatnonzero(ok)
        moved_to, moved = corners_on_edges(gray, gx, gy, refined[junctions])
        refined[junctions[moved]] = moved_to[moved]
    return np.where(ok[:, None], refined, peak)


def _junction_refinement(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, peak: np.ndarray, win: int,
                         junction_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """cv2.cornerSubPix in a (2 win + 1)^2 window from the peaks (N, 2): positions (N, 2) and
    where they hold (N,) bool (converged inside the window and :func:`_is_junction`)."""

    def subpix(start: np.ndarray, iters: int) -> np.ndarray:
        pts = start.astype(np.float32).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, iters, 1e-3)
        cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), criteria)
        return pts[:, 0, :].astype(np.float64)

    # Two passes for speed: a short one everywhere, then convergence only where the junction
    # model looks plausible (most texture points are rejected after the short pass).
    refined = subpix(peak, 8)
    moved_ok = np.all(np.isfinite(refined), axis=1) & (np.abs(refined - peak).max(axis=1) < win)
    cand = np.flatnonzero(moved_ok)
    cand = cand[_junction_residual(gx, gy, refined[cand], win) < 2.0 * junction_tol]
    ok = np.zeros(len(peak), bool)
    if len(cand):
        refined[cand] = subpix(refined[cand], 40)
        step = np.abs(refined[cand] - peak[cand]).max(axis=1)
        good = np.all(np.isfinite(refined[cand]), axis=1) & (step < win)
        good[good] = _is_junction(gx, gy, refined[cand[good]], win, junction_tol)
        ok[cand[good]] = True
    return refined, ok


def detect_corners(gray: np.ndarray, config: FeatureConfig = FeatureConfig()) -> np.ndarray:
    """Harris interest points with sub-pixel positions.

    gray: (H, W) float32 in [0, 1] (see :func:`to_gray`).
    Returns (N, 2) float64 ``(x, y)``, N <= ``config.max_corners``, sorted by Harris response
    (strongest first), pairwise at least ``config.min_distance`` apart at detection (3x3 local
    maxima of the response above ``config.quality_level`` times the best one), at least
    ``config.border`` px from the image edge.
    Sub-pixel positions: ``cv2.cornerSubPix`` over a ``(2 * subpixel_window + 1)``² window where
    the image is a junction (its model fits), the quadratic peak of the Harris response elsewhere
    (see :func:`_refine_subpixel`; ``subpixel_window = 0`` keeps the peak everywhere).
    Empty, tiny or flat images give a (0, 2) array (and an INFO log record saying why).
    """
    return detect_corners_with_response(gray, config)[0]


@functools.cache
def _remap_is_exact() -> bool:
    """Whether cv2.remap (INTER_LINEAR, float maps) interpolates at the exact position: OpenCV
    5.x does; 4.x (4.10, nerfstudio's pin) first rounds the position to 1/32 px, so the
    descriptors, and every match decided on a margin after them, would differ by version."""
    ramp = np.array([[0.0, 64.0], [0.0, 64.0]], np.float32)
    sample = cv2.remap(ramp, np.full((1, 1), 0.3, np.float32), np.zeros((1, 1), np.float32), cv2.INTER_LINEAR)
    return abs(float(sample[0, 0]) - 19.2) < 1e-3  # 1/32 px steps give 20.0


@njit(cache=True)
def _sample_patches(gray, xs, ys, out):
    """out[i, j] = gray bilinearly sampled at (xs[i, j], ys[i, j]), edges replicated."""
    for i in range(xs.shape[0]):
        for j in range(xs.shape[1]):
            out[i, j] = sample_bilinear(gray, np.float64(xs[i, j]), np.float64(ys[i, j]))


def _bilinear_patches(
    gray: np.ndarray, points: np.ndarray, patch_size: int, spacing: float = 1.0
) -> np.ndarray:
    """Sample (N, P*P) float32 patches centred on sub-pixel points by bilinear interpolation.

    cv2.remap with one output row per point where it interpolates at the exact position
    (OpenCV 5.x), :func:`sample_bilinear` otherwise (:func:`_remap_is_exact`): the same
    descriptors on either OpenCV to float32 rounding. Samples outside the image are clamped
    to the edge (the caller marks those patches invalid).
    """
    r = patch_size // 2
    d = np.arange(-r, r + 1, dtype=np.float32) * np.float32(spacing)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    out = np.empty((len(points), patch_size * patch_size), np.float32)
    exact = _remap_is_exact()
    # remap needs maps smaller than 32767 in each dimension.
    for start in range(0, len(points), _REMAP_ROWS):
        p = points[start : start + _REMAP_ROWS].astype(np.float32)
        xs = p[:, 0:1] + dx.reshape(1, -1)  # (n, P*P), row-major patch order
        ys = p[:, 1:2] + dy.reshape(1, -1)
        if exact:
            out[start : start + len(p)] = cv2.remap(
                gray, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        else:
            _sample_patches(np.ascontiguousarray(gray, np.float32), xs, ys, out[start : start + len(p)])
    return out


def describe_scaled(
    gray: np.ndarray,
    points: np.ndarray,
    patch_size: int,
    scale: float,
    *,
    min_std: float = DEFAULT_MIN_PATCH_STD,
) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`describe`, with the P x P samples spaced ``scale`` px apart.

    Matches a patch of another image seen ``scale`` times smaller (zoom, distance change).
    """
    return describe(gray, points, patch_size, min_std=min_std, spacing=scale)


def describe(
    gray: np.ndarray,
    points: np.ndarray,
    patch_size: int = MatchingConfig().patch_size,
    *,
    min_std: float = DEFAULT_MIN_PATCH_STD,
    spacing: float = 1.0,
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
    r = (patch_size // 2) * float(spacing)
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

    gray32 = np.ascontiguousarray(gray, np.float32)
    patches = _bilinear_patches(gray32, pts[inside], patch_size, spacing)
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
    return Features(points, desc, valid, response, (int(gray.shape[0]), int(gray.shape[1])), gray)
