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
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .config import FeatureConfig, MatchingConfig
from .errors import StereoseedError

__all__ = [
    "Features",
    "to_gray",
    "detect_corners",
    "detect_corners_with_response",
    "describe",
    "describe_scaled",
    "extract_features",
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
        (:func:`stereoseed.matching.align_matches`); None if not available.
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
            f"image of shape {img.shape} is not a grey (H, W), BGR (H, W, 3) or BGRA (H, W, 4) "
            "image"
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
    close = cKDTree(pts).query_pairs(_SAME_POINT_PX, output_type="ndarray")
    if len(close):
        weaker = np.unique(close.max(axis=1))  # pairs (i, j) with i < j: j is the weaker
        keep = np.ones(len(pts), bool)
        keep[weaker] = False
        pts, response = pts[keep], response[keep]
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


def _junction_residual(gx: np.ndarray, gy: np.ndarray, q: np.ndarray, win: int,
                       strong_fraction: float = 0.0) -> np.ndarray:
    """How badly the cornerSubPix model fits at q: (N, 2) -> (N,) float64 in [0, 1].

    gx, gy: (H, W) float32 image gradients. Returns
    sum_p (g_p . (q - p))^2 / sum_p |g_p|^2 |q - p|^2 over the (2 win + 1)^2 pixels p around q:
    0 when every gradient g_p is orthogonal to q - p (an ideal junction at q).
    strong_fraction > 0 keeps only the pixels whose gradient is at least that fraction of the
    window's strongest: the residual of the high-contrast edges alone.
    """
    h, w = gx.shape
    qi = np.rint(q).astype(np.int64)
    qi[:, 0] = np.clip(qi[:, 0], win, w - 1 - win)
    qi[:, 1] = np.clip(qi[:, 1], win, h - 1 - win)
    d = np.arange(-win, win + 1)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    flat = (qi[:, 1:2] + dy.reshape(1, -1)) * w + qi[:, 0:1] + dx.reshape(1, -1)  # (N, K)
    g_x, g_y = gx.reshape(-1)[flat], gy.reshape(-1)[flat]
    vx = (q[:, 0:1] - qi[:, 0:1] - dx.reshape(1, -1)).astype(np.float32)
    vy = (q[:, 1:2] - qi[:, 1:2] - dy.reshape(1, -1)).astype(np.float32)
    g2 = g_x * g_x + g_y * g_y
    along = (g_x * vx + g_y * vy) ** 2
    full = g2 * (vx * vx + vy * vy)
    if strong_fraction > 0.0:
        weak = g2 < np.float32(strong_fraction**2) * g2.max(axis=1, keepdims=True)
        along[weak] = 0.0
        full[weak] = 0.0
    num = along.sum(axis=1, dtype=np.float64)
    den = full.sum(axis=1, dtype=np.float64)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)


def _is_junction(gx: np.ndarray, gy: np.ndarray, q: np.ndarray, win: int, tol: float) -> np.ndarray:
    """Where cornerSubPix's position q (N, 2) can be trusted: (N,) bool.

    Either the whole window fits the junction model (residual < tol), or a high-contrast
    junction on a textured surface (a dark square's corner on a textured face): the window as a
    whole fits loosely (< 2 tol) and its strong edges alone (gradients >= half the window's
    strongest) fit tightly (< tol / 2). Measured on the synthetic textured box (14 images, σ 0):
    the square corners admitted go from 63 % to 91 % (median error 0.27 px against 1.1 px for
    the Harris peak), other detections from 2.9 % to 4.5 %; on templeSparseRing the admitted
    share goes from 6 % to 9 % (a plain 2 tol would admit 27 %).
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

    Textured blobs and junctions need different refinements. Measured on the synthetic box (20
    degrees between views, detections of image 0 within 1 px / 0.5 px of the true position of a
    detection of image 1): cornerSubPix alone 449 / 243, Harris peak alone 687 / 516 on the
    textured scene; on the plain box's square corners cornerSubPix 119 / 111 but the peak only
    104 / 70. Every point gets the quadratic Harris peak; cv2.cornerSubPix (window
    (2 win + 1)^2, started from the peak) replaces it where the junction model fits
    (:func:`_is_junction`) and the refinement stayed inside its window; where it does not,
    a window half as wide is tried the same way. With ``edge_corners`` a junction then moves to
    the intersection of its two edges where both are found and straight (:func:`_edge_corners`).
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
    # A square's corner on a textured face often fails the model in the full window (the texture
    # around it) but holds in a smaller one: on the synthetic box a (2 * 3 + 1)^2 window admits a
    # third of the corners the 11 x 11 one refused, and 0.4 % of templeSparseRing's points.
    smaller = (win + 1) // 2
    for size in (win, smaller) if 2 <= smaller < win else (win,):
        rest = np.flatnonzero(~ok)
        if len(rest) == 0:
            break
        refined[rest], ok[rest] = _junction_refinement(gray, gx, gy, peak[rest], size, junction_tol)
    if edge_corners and ok.any():
        junctions = np.flatnonzero(ok)
        moved_to, moved = _edge_corners(gray, gx, gy, refined[junctions])
        refined[junctions[moved]] = moved_to[moved]
    return np.where(ok[:, None], refined, peak)


# Corners as the intersection of their two edges: where the junction model holds, the two edge
# directions come from the gradients in a (2 * _EDGE_WINDOW + 1)^2 window (the apex excluded), each
# edge is located by sub-pixel intensity profiles across it _EDGE_FROM..._EDGE_TO px from the
# corner, a straight line is fitted to those edge points, and the lines are intersected. Away from
# the apex an edge is a clean step, so its line does not carry cornerSubPix's bias at a blurred L
# corner (measured on the synthetic box, started 0.4 px off: median distance to the true corner
# 0.22 -> 0.11 px on the plain box, 0.34 -> 0.20 px on the textured one).
_EDGE_WINDOW = 6
_EDGE_APEX = 1.5  # px around the corner whose gradients mix both edges
_EDGE_FROM, _EDGE_TO, _EDGE_STEP = 2.0, 10.0, 0.5  # profile positions along an edge (px)
_EDGE_PROFILE_HALF = 2.5  # half-length of a profile across the edge (px), sampled every 0.25 px
_EDGE_MIN_ANGLE_DEG = 25.0  # the two edges must differ by this much to intersect well
_EDGE_MAX_SCATTER = 0.3  # px rms of the edge points about their line: a straight edge
_EDGE_MAX_SHIFT = 1.0  # px from the junction's position: farther is another structure


@njit(cache=True)
def sample_bilinear(img: np.ndarray, x: float, y: float) -> float:
    """Bilinear sample of img at (x, y), edges replicated (pixel centres at integers)."""
    h, w = img.shape
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0 = min(int(x), w - 2) if w > 1 else 0
    y0 = min(int(y), h - 2) if h > 1 else 0
    fx, fy = x - x0, y - y0
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    top = img[y0, x0] * (1.0 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1.0 - fx) + img[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


@njit(cache=True)
def _edge_line(gray, cx, cy, nx, ny, sides, half, s_from, s_to, s_step, max_scatter):
    """Sub-pixel edge points along the edge of normal (nx, ny) leaving (cx, cy) on ``sides``
    (+1, -1 or both: 0) and their total-least-squares line. Returns (ok, nx, ny, c): n.p = c."""
    h, w = gray.shape
    dx, dy = -ny, nx
    n_t = int(round(2 * half / 0.25)) + 1
    vals = np.empty(n_t)
    px = np.empty(64)
    py = np.empty(64)
    count = 0
    for side in (1.0, -1.0):
        if sides != 0 and side != sides:
            continue
        s = s_from
        while s <= s_to + 1e-9 and count < 64:
            bx = cx + side * s * dx
            by = cy + side * s * dy
            inside = True
            for k in range(n_t):
                t = -half + 0.25 * k
                x = bx + t * nx
                y = by + t * ny
                if x < 0.0 or y < 0.0 or x >= w - 1.0 or y >= h - 1.0:
                    inside = False
                    break
                vals[k] = sample_bilinear(gray, x, y)
            s += s_step
            if not inside:
                continue
            best, k0 = 0.0, 0
            for k in range(n_t - 1):
                d = abs(vals[k + 1] - vals[k])
                if d > best:
                    best, k0 = d, k
            if best <= 0.0:  # a flat profile
                continue
            # centroid of the derivative's main lobe (within 1.25 px of its peak); a step holds
            # most of the profile's variation there, blurred or not (texture or a second edge
            # spreads it)
            num, den, total = 0.0, 0.0, 0.0
            t0 = -half + 0.25 * (k0 + 0.5)
            for k in range(n_t - 1):
                t = -half + 0.25 * (k + 0.5)
                d = abs(vals[k + 1] - vals[k])
                total += d
                if abs(t - t0) <= 1.25:
                    num += d * t
                    den += d
            if den < 0.6 * total:
                continue
            off = num / den
            px[count] = bx + off * nx
            py[count] = by + off * ny
            count += 1
    if count < 5:
        return False, 0.0, 0.0, 0.0
    mx = px[:count].mean()
    my = py[:count].mean()
    sxx, sxy, syy = 0.0, 0.0, 0.0
    for i in range(count):
        ex, ey = px[i] - mx, py[i] - my
        sxx += ex * ex
        sxy += ex * ey
        syy += ey * ey
    sxx /= count
    sxy /= count
    syy /= count
    # smallest eigenvalue and its eigenvector: the line's normal
    tr = sxx + syy
    disc = np.sqrt(max((sxx - syy) ** 2 / 4.0 + sxy * sxy, 0.0))
    lam_min = tr / 2.0 - disc
    if np.sqrt(max(lam_min, 0.0)) > max_scatter:
        return False, 0.0, 0.0, 0.0
    if abs(sxy) > 1e-12:
        ex, ey = lam_min - syy, sxy
    elif sxx < syy:
        ex, ey = 1.0, 0.0
    else:
        ex, ey = 0.0, 1.0
    norm = np.sqrt(ex * ex + ey * ey)
    ex /= norm
    ey /= norm
    return True, ex, ey, ex * mx + ey * my


@njit(cache=True)
def _edge_corner_kernel(gray, gx, gy, pts, radius, apex, half, s_from, s_to, s_step, min_angle_deg,
                        max_scatter, max_shift, out, ok):
    h, w = gray.shape
    size = (2 * radius + 1) ** 2
    xs = np.empty(size)
    ys = np.empty(size)
    ms = np.empty(size)
    c2 = np.empty(size)
    s2 = np.empty(size)
    in_a = np.empty(size, np.bool_)  # which of the two edge orientations a gradient belongs to
    cos_sep = np.cos(np.radians(2.0 * min_angle_deg))
    for i in range(pts.shape[0]):
        cx, cy = pts[i, 0], pts[i, 1]
        ix, iy = int(round(cx)), int(round(cy))
        ok[i] = False
        if ix - radius < 1 or iy - radius < 1 or ix + radius >= w - 1 or iy + radius >= h - 1:
            continue
        mmax = 0.0
        for y in range(iy - radius, iy + radius + 1):
            for x in range(ix - radius, ix + radius + 1):
                m = np.hypot(gx[y, x], gy[y, x])
                if m > mmax:
                    mmax = m
        if mmax <= 0.0:
            continue
        n = 0
        for y in range(iy - radius, iy + radius + 1):
            for x in range(ix - radius, ix + radius + 1):
                gxv, gyv = gx[y, x], gy[y, x]
                m = np.hypot(gxv, gyv)
                if m >= 0.5 * mmax and np.hypot(x - cx, y - cy) >= apex:
                    xs[n], ys[n], ms[n] = x, y, m
                    c2[n] = (gxv * gxv - gyv * gyv) / (m * m)  # doubled gradient angle
                    s2[n] = 2.0 * gxv * gyv / (m * m)
                    n += 1
        if n < 8:
            continue
        # two edge orientations: 2-means on the doubled angles, from the strongest gradient and
        # the one least like it
        a = int(np.argmax(ms[:n]))
        ax, ay = c2[a], s2[a]
        b, worst = 0, 2.0
        for j in range(n):
            d = ax * c2[j] + ay * s2[j]
            if d < worst:
                b, worst = j, d
        bx, by = c2[b], s2[b]
        good = True
        for _ in range(6):
            sax, say, sbx, sby = 0.0, 0.0, 0.0, 0.0
            na, nb = 0, 0
            for j in range(n):
                if ax * c2[j] + ay * s2[j] >= bx * c2[j] + by * s2[j]:
                    sax += ms[j] * c2[j]
                    say += ms[j] * s2[j]
                    na += 1
                else:
                    sbx += ms[j] * c2[j]
                    sby += ms[j] * s2[j]
                    nb += 1
            if na < 4 or nb < 4:
                good = False
                break
            la, lb = np.hypot(sax, say), np.hypot(sbx, sby)
            if la == 0.0 or lb == 0.0:
                good = False
                break
            ax, ay, bx, by = sax / la, say / la, sbx / lb, sby / lb
        if not good or ax * bx + ay * by > cos_sep:
            continue
        for j in range(n):
            in_a[j] = ax * c2[j] + ay * s2[j] >= bx * c2[j] + by * s2[j]
        normals = np.empty((2, 2))
        sides = np.zeros(2, np.int64)
        for e in range(2):
            vx, vy = (ax, ay) if e == 0 else (bx, by)
            th = 0.5 * np.arctan2(vy, vx)
            normals[e, 0], normals[e, 1] = np.cos(th), np.sin(th)
            # which way the edge leaves the corner (an L corner: one side; an X junction: both)
            side, total = 0.0, 0.0
            for j in range(n):
                if in_a[j] == (e == 0):
                    along = (xs[j] - cx) * (-normals[e, 1]) + (ys[j] - cy) * normals[e, 0]
                    side += ms[j] * along
                    total += ms[j] * abs(along)
            sides[e] = 0 if abs(side) < 0.5 * total else (1 if side > 0 else -1)
        # Where the edges leaving the corner make an acute angle, a profile across one of them
        # s px out meets the other at t = s tan(angle): start where the profile's lobe stays
        # clear of it (an obtuse L corner has no such crossing; an X junction always has one).
        cos_rays = normals[0, 1] * normals[1, 1] + normals[0, 0] * normals[1, 0]  # = d0 . d1
        if sides[0] != 0 and sides[1] != 0:
            cos_rays *= sides[0] * sides[1]
        else:
            cos_rays = abs(cos_rays)
        start = s_from
        if cos_rays > 0.0:
            start = max(s_from, (half + 1.25) * cos_rays / np.sqrt(max(1.0 - cos_rays * cos_rays, 1e-12)))
        if s_to - start < 2.0:
            continue
        lines = np.empty((2, 3))
        for e in range(2):
            fit, lx, ly, lc = _edge_line(gray, cx, cy, normals[e, 0], normals[e, 1], sides[e], half, start, s_to,
                                         s_step, max_scatter)
            if not fit:
                good = False
                break
            lines[e, 0], lines[e, 1], lines[e, 2] = lx, ly, lc
        if not good:
            continue
        det = lines[0, 0] * lines[1, 1] - lines[0, 1] * lines[1, 0]
        if abs(det) < 1e-6:
            continue
        qx = (lines[0, 2] * lines[1, 1] - lines[0, 1] * lines[1, 2]) / det
        qy = (lines[0, 0] * lines[1, 2] - lines[0, 2] * lines[1, 0]) / det
        if np.hypot(qx - cx, qy - cy) > max_shift:
            continue
        out[i, 0], out[i, 1] = qx, qy
        ok[i] = True


def _edge_corners(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Junctions (N, 2) moved to the intersection of their two edges where both edges are found
    and straight (see _EDGE_WINDOW). Returns (positions (N, 2), moved (N,) bool)."""
    out = np.array(points, np.float64, copy=True)
    ok = np.zeros(len(out), np.bool_)
    if len(out):
        _edge_corner_kernel(np.ascontiguousarray(gray, np.float32), gx, gy, out.copy(), _EDGE_WINDOW, _EDGE_APEX,
                            _EDGE_PROFILE_HALF, _EDGE_FROM, _EDGE_TO, _EDGE_STEP, _EDGE_MIN_ANGLE_DEG,
                            _EDGE_MAX_SCATTER, _EDGE_MAX_SHIFT, out, ok)
    return out, ok


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
    Empty, tiny or flat images give a (0, 2) array and a RuntimeWarning.
    """
    return detect_corners_with_response(gray, config)[0]


def _bilinear_patches(
    gray: np.ndarray, points: np.ndarray, patch_size: int, spacing: float = 1.0
) -> np.ndarray:
    """Sample (N, P*P) float32 patches centred on sub-pixel points by bilinear interpolation.

    cv2.remap with one output row per point (positions quantised to 1/32 px, far below the
    detector's accuracy). Samples outside the image are clamped to the edge (the caller marks
    those patches invalid).
    """
    r = patch_size // 2
    d = np.arange(-r, r + 1, dtype=np.float32) * np.float32(spacing)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    out = np.empty((len(points), patch_size * patch_size), np.float32)
    # remap needs maps smaller than 32767 in each dimension.
    for start in range(0, len(points), _REMAP_ROWS):
        p = points[start : start + _REMAP_ROWS].astype(np.float32)
        xs = p[:, 0:1] + dx.reshape(1, -1)  # (n, P*P), row-major patch order
        ys = p[:, 1:2] + dy.reshape(1, -1)
        out[start : start + len(p)] = cv2.remap(
            gray, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
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
