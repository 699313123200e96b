"""A lens: OpenCV's radial-tangential distortion model (Brown-Conrady, 5 coefficients).

Coefficients ``d = (k1, k2, p1, p2[, k3])`` (k3 = 0 when omitted; ``()`` = no lens) act on
normalized image coordinates ``(x, y) = (X / Z, Y / Z)`` of a point in the camera frame::

    r2 = x^2 + y^2,   c = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x_d = x c + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y c + p1 (r2 + 2 y^2) + 2 p2 x y

and the distorted pixel is ``K (x_d, y_d, 1)`` with the camera's pinhole K (skew allowed; note that
OpenCV's own functions ignore K's skew). Pixel (0, 0) is the centre of the top-left pixel.

"Undistorted" pixels are those of the pinhole camera K [R | t]; "distorted" pixels are those of
the image the lens forms. :func:`undistort_normalized` inverts the model by Newton's method on the
principal branch (the one containing the origin), which covers any real frame for
``|k1| <= 0.3``; a point the iteration cannot invert comes back as NaN.

Shapes: points (N, 2) or (N, 3) float64; K (3, 3); images (H, W) or (H, W, C).
"""
from __future__ import annotations

import cv2
import numpy as np
from numba import njit, prange

__all__ = [
    "lens_coefficients",
    "lens_index",
    "principal_r2",
    "lens_problem",
    "distort_normalized",
    "undistort_normalized",
    "distort_pixels",
    "undistort_pixels",
    "project_distorted",
    "undistortion_maps",
    "undistort_image",
]

_ITERATIONS = 20  # Newton steps at most; 3-6 reach 1e-15 inside a frame


def lens_coefficients(d) -> np.ndarray:
    """(k1, k2, p1, p2[, k3]) or () -> (5,) float64 (k1, k2, p1, p2, k3); () gives zeros."""
    d = np.asarray(d, dtype=np.float64).ravel()
    if d.size == 0:
        return np.zeros(5)
    if d.size not in (4, 5):
        raise ValueError(f"lens distortion needs 4 or 5 coefficients (k1, k2, p1, p2[, k3]), "
                         f"got {d.size}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"lens distortion coefficients must be finite, got {d.tolist()}")
    return np.concatenate([d, np.zeros(5 - d.size)])


def distort_normalized(xy: np.ndarray, d) -> np.ndarray:
    """Apply the lens to normalized coordinates: xy (N, 2) -> (N, 2) distorted normalized."""
    k1, k2, p1, p2, k3 = lens_coefficients(d)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    c = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    a1 = 2.0 * x * y
    xd = x * c + p1 * a1 + p2 * (r2 + 2.0 * x * x)
    yd = y * c + p1 * (r2 + 2.0 * y * y) + p2 * a1
    return np.stack([xd, yd], axis=1)


@njit(cache=True, nogil=True)
def lens_jacobian(x, y, k1, k2, p1, p2, k3):
    """d(x_d, y_d) / d(x, y) at undistorted (x, y): the symmetric (jxx, jxy, jyy)."""
    x2 = x * x
    y2 = y * y
    r2 = x2 + y2
    c = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dc = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dc / d(r2)
    jxx = c + 2.0 * x2 * dc + 2.0 * p1 * y + 6.0 * p2 * x
    jxy = 2.0 * x * y * dc + 2.0 * p1 * x + 2.0 * p2 * y
    jyy = c + 2.0 * y2 * dc + 6.0 * p1 * y + 2.0 * p2 * x
    return jxx, jxy, jyy


@njit(cache=True, nogil=True)
def undistort_point_from(xd, yd, x, y, k1, k2, p1, p2, k3, r2_max, iterations):
    """Newton inversion of the lens for one point from the initial guess (x, y):
    (x_d, y_d) -> (x, y, ok).

    Stops once a Newton step is below 1e-6 (quadratic convergence: the error left is ~1e-12
    times the lens's second derivative, < 1e-12 for |k1| <= 0.3 in a frame). ok is False
    (x, y NaN) when that does not happen within ``iterations`` steps, the Jacobian degenerates,
    or the solution is off the principal branch (r^2 >= r2_max, :func:`principal_r2`).
    """
    for _ in range(iterations):
        x2 = x * x
        y2 = y * y
        xy = x * y
        r2 = x2 + y2
        c = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dc = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dc / d(r2)
        fx = x * c + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2) - xd
        fy = y * c + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy - yd
        jxx = c + 2.0 * x2 * dc + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = 2.0 * xy * dc + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = c + 2.0 * y2 * dc + 6.0 * p1 * y + 2.0 * p2 * x
        det = jxx * jyy - jxy * jxy
        if not abs(det) > 1e-12:
            return np.nan, np.nan, False
        sx = (jyy * fx - jxy * fy) / det
        sy = (jxx * fy - jxy * fx) / det
        x -= sx
        y -= sy
        if sx * sx + sy * sy < 1e-12:
            if x * x + y * y < r2_max:
                return x, y, True
            return np.nan, np.nan, False
    return np.nan, np.nan, False


@njit(cache=True, nogil=True)
def undistort_point(xd, yd, k1, k2, p1, p2, k3, r2_max, iterations):
    """:func:`undistort_point_from` starting from ``(x_d, y_d) / c(r_d)`` (one fixed-point
    step from the distorted point: the principal branch's side)."""
    r2 = xd * xd + yd * yd
    c = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if not c > 0.0:
        return np.nan, np.nan, False
    return undistort_point_from(xd, yd, xd / c, yd / c, k1, k2, p1, p2, k3, r2_max, iterations)


def principal_r2(d) -> float:
    """Squared normalized radius where the radial distortion r c(r) stops increasing (the first
    root of d(r c)/dr = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6); inf if it never does. Inside it the
    lens is one-to-one (tangential terms aside): the principal branch the undistortion keeps."""
    k1, k2, _, _, k3 = lens_coefficients(d)
    roots = np.roots(np.trim_zeros([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0], "f"))
    real = roots[(np.abs(roots.imag) < 1e-12 * np.maximum(1.0, np.abs(roots))) & (roots.real > 0)]
    return float(real.real.min()) if real.size else np.inf


# a lens moving an image corner by more than its distance from the principal point (twice as
# far out, or onto the centre) is no lens of this model but a typo (k1 = 50 for 0.50)
MAX_CORNER_SHIFT = 1.0


def lens_problem(d, K: np.ndarray, image_size: tuple[float, float]) -> str | None:
    """Why ``d`` cannot be the lens of camera K's images of ``image_size`` (width, height), or
    None when it can: the radial map r_d(r) = r c(r) must be increasing over the image (up to
    the corners' radius, and far enough to reach the photo's corners: else the image folds back
    onto itself and no pixel has one undistorted position), and no image corner may move by
    more than its distance from the principal point (``MAX_CORNER_SHIFT``). The message names
    the coefficient that weighs most there. A pure function: nothing is read or raised."""
    k1, k2, p1, p2, k3 = coeffs = lens_coefficients(d)
    if not np.any(coeffs):
        return None
    w, h = float(image_size[0]), float(image_size[1])
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    xy = _to_normalized(corners, K)
    r_corner = float(np.max(np.linalg.norm(xy, axis=1)))
    r2_fold = principal_r2(coeffs)
    if np.isfinite(r2_fold):
        r_fold = float(np.sqrt(r2_fold))
        reach = r_fold * (1.0 + r2_fold * (k1 + r2_fold * (k2 + r2_fold * k3)))  # the largest r_d
        if r_fold <= r_corner or reach <= r_corner:
            name, value = _weightiest(coeffs, r_fold)
            return (f"is not a lens over the image: its radial distortion r_d(r) stops increasing at r = {r_fold:.3g} "
                    f"(normalised), inside the image (corners at r = {r_corner:.3g}), so the image folds back onto "
                    f"itself ({name} = {value:g})")
    shift = np.linalg.norm(distort_normalized(xy, coeffs) - xy, axis=1) / np.maximum(np.linalg.norm(xy, axis=1), 1e-12)
    if not np.max(shift) <= MAX_CORNER_SHIFT:
        name, value = _weightiest(coeffs, r_corner)
        return (f"moves an image corner by {np.max(shift):.3g} times its distance from the principal point (at most "
                f"{MAX_CORNER_SHIFT:g} for a lens: {name} = {value:g})")
    return None


def _weightiest(coeffs: np.ndarray, r: float) -> tuple[str, float]:
    """(name, value) of the coefficient whose term is the largest at normalised radius r."""
    k1, k2, p1, p2, k3 = coeffs
    terms = {"k1": (k1, k1 * r ** 2), "k2": (k2, k2 * r ** 4), "k3": (k3, k3 * r ** 6),
             "p1": (p1, 3.0 * p1 * r), "p2": (p2, 3.0 * p2 * r)}
    name = max(terms, key=lambda n: abs(terms[n][1]))
    return name, float(terms[name][0])


@njit(cache=True, nogil=True)
def undistort_pixel_centre(xd, yd, lens, r2_max):
    """A renderer's start for the sub-samples of one pixel: the pixel centre's undistorted
    normalized position (xd, yd distorted) and the lens Jacobian there, ``lens`` (5,):
    (x, y, jxx, jxy, jyy, det, ok); ok False where the centre has no principal-branch inverse
    or the Jacobian degenerates (each sub-sample is then inverted from scratch)."""
    x, y, ok = undistort_point(xd, yd, lens[0], lens[1], lens[2], lens[3], lens[4], r2_max, _ITERATIONS)
    jxx = jxy = jyy = det = 0.0
    if ok:
        jxx, jxy, jyy = lens_jacobian(x, y, lens[0], lens[1], lens[2], lens[3], lens[4])
        det = jxx * jyy - jxy * jxy
        ok = abs(det) > 1e-12
    return x, y, jxx, jxy, jyy, det, ok


@njit(cache=True, nogil=True)
def undistort_sample(xd, yd, xdc, ydc, xc, yc, jxx, jxy, jyy, det, centre_ok, lens, r2_max):
    """A sub-sample's undistorted normalized position (x, y, ok), started from the linearisation
    at its pixel centre (:func:`undistort_pixel_centre`: one Newton step is then left)."""
    if centre_ok:
        ex = xd - xdc
        ey = yd - ydc
        return undistort_point_from(xd, yd, xc + (jyy * ex - jxy * ey) / det, yc + (jxx * ey - jxy * ex) / det,
                                    lens[0], lens[1], lens[2], lens[3], lens[4], r2_max, _ITERATIONS)
    return undistort_point(xd, yd, lens[0], lens[1], lens[2], lens[3], lens[4], r2_max, _ITERATIONS)


@njit(parallel=True, cache=True)
def _undistort_kernel(xy_d, coeffs, r2_max, iterations):
    n = xy_d.shape[0]
    out = np.empty((n, 2), dtype=np.float64)
    k1, k2, p1, p2, k3 = coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4]
    for i in prange(n):
        x, y, _ = undistort_point(xy_d[i, 0], xy_d[i, 1], k1, k2, p1, p2, k3, r2_max,
                                  iterations)
        out[i, 0] = x
        out[i, 1] = y
    return out


def undistort_normalized(xy_d: np.ndarray, d, iterations: int = _ITERATIONS) -> np.ndarray:
    """Invert :func:`distort_normalized` (Newton): xy_d (N, 2) -> (N, 2); NaN rows where the
    principal-branch inverse does not exist (far outside the frame of a strong lens)."""
    coeffs = lens_coefficients(d)
    xy_d = np.ascontiguousarray(np.asarray(xy_d, dtype=np.float64).reshape(-1, 2))
    if not np.any(coeffs):
        return xy_d.copy()
    return _undistort_kernel(xy_d, coeffs, principal_r2(coeffs), int(iterations))


def _to_normalized(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> normalized (N, 2) through K^-1 (K upper triangular, K[2] = (0, 0, 1))."""
    K = np.asarray(K, dtype=np.float64)
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    y = (pixels[:, 1] - cy) / fy
    x = (pixels[:, 0] - cx - s * y) / fx
    return np.stack([x, y], axis=1)


def _to_pixels(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalized (N, 2) -> pixels (N, 2) through K (skew included)."""
    K = np.asarray(K, dtype=np.float64)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


def distort_pixels(pixels: np.ndarray, K: np.ndarray, d) -> np.ndarray:
    """Undistorted (pinhole) pixels (N, 2) -> distorted pixels (N, 2) of the same K."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    return _to_pixels(distort_normalized(_to_normalized(pixels, K), d), K)


def undistort_pixels(pixels: np.ndarray, K: np.ndarray, d,
                     iterations: int = _ITERATIONS) -> np.ndarray:
    """Distorted pixels (N, 2) -> undistorted (pinhole) pixels (N, 2) of the same K (NaN where
    the inverse does not exist, see :func:`undistort_normalized`)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    xy = undistort_normalized(_to_normalized(pixels, K), d, iterations)
    return _to_pixels(xy, K)


def project_distorted(K: np.ndarray, R: np.ndarray, t: np.ndarray, d,
                      points: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> distorted pixels (N, 2) of the camera K [R | t] behind lens d.

    Equals ``cv2.projectPoints(points, rvec(R), t, K, d)`` for a K without skew. Points on the
    principal plane give inf / NaN; points behind the camera are projected all the same (check
    depths separately).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    Xc = points @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64).ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = Xc[:, :2] / Xc[:, 2:3]
        return _to_pixels(distort_normalized(xy, d), K)


def undistortion_maps(K: np.ndarray, d, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (H, W) float32 x and y: for each pixel of the undistorted image (camera K,
    no lens) the position to sample in the distorted image. size = (width, height).

    ``cv2.initUndistortRectifyMap(K, d, None, K, size, CV_32FC1)``; OpenCV ignores a skewed K's
    skew in the distortion, so for a K with skew the maps are computed with
    :func:`distort_pixels` instead (the same model, skew honoured).
    """
    K = np.asarray(K, dtype=np.float64)
    coeffs = lens_coefficients(d)
    width, height = int(size[0]), int(size[1])
    if K[0, 1] == 0.0:
        return cv2.initUndistortRectifyMap(K, coeffs, None, K, (width, height), cv2.CV_32FC1)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    src = distort_pixels(np.stack([u.ravel(), v.ravel()], axis=1), K, coeffs)
    return (src[:, 0].reshape(height, width).astype(np.float32),
            src[:, 1].reshape(height, width).astype(np.float32))


def undistort_image(image: np.ndarray, K: np.ndarray, d,
                    maps: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The image a pinhole camera K would have taken: same size, same K, bilinear, black outside
    the distorted frame. maps: :func:`undistortion_maps` of this K, d and size, to reuse."""
    image = np.asarray(image)
    if maps is None:
        maps = undistortion_maps(K, d, (image.shape[1], image.shape[0]))
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def lens_index(image: int, rig: bool) -> int:
    """Which of the calibration's two lenses image ``image`` of a sequence was taken through:
    image 0 the first camera's and every later one the second's (the moving camera), or on a
    rig walk (left and right images interleaved) the side's."""
    return image % 2 if rig else min(image, 1)
