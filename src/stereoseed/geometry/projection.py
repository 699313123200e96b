"""Pinhole camera geometry on raw arrays: projection, centre, P <-> K[R|t], fundamental matrix
(:class:`stereoseed.geometry.camera.Camera` is the value type built on them).

Conventions, written once for the whole package:

* ``P`` is a (3, 4) float64 matrix mapping homogeneous world points to homogeneous pixels:
  ``lambda * (u, v, 1) = P @ (X, Y, Z, 1)``.
* Pixel (0, 0) is the centre of the top-left pixel, x to the right, y down (OpenCV's).
* ``R, t`` are ``cam_from_world``: a world point X sits at ``R @ X + t`` in the camera frame;
  the camera centre is ``C = -R.T @ t``.
* ``F`` maps a pixel x1 of image 1 to its epipolar line in image 2: ``x2.T @ F @ x1 = 0``.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "to_homogeneous",
    "is_finite_camera",
    "project",
    "project_homogeneous",
    "project_per_observation",
    "point_jacobian",
    "backproject",
    "viewing_direction",
    "camera_center",
    "depths",
    "compose_projection",
    "decompose_projection",
    "normalize_projection",
    "fundamental_from_projections",
    "epipolar_distances",
    "skew",
    "rotation_angle_deg",
    "intrinsics_turned_180",
]


def is_finite_camera(P: np.ndarray) -> bool:
    """Whether P (3, 4) is a finite projective camera: finite entries, a non-singular left 3x3
    block (a camera centre that is a point, not at infinity)."""
    P = np.asarray(P, dtype=np.float64)
    return bool(np.all(np.isfinite(P)) and abs(np.linalg.det(P[:, :3])) > 0)


def to_homogeneous(points: np.ndarray) -> np.ndarray:
    """Append a column of ones. points: (N, D) -> (N, D+1)."""
    points = np.asarray(points, dtype=np.float64)
    return np.hstack([points, np.ones((points.shape[0], 1))])


def project(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Project world points to pixels.

    P: (3, 4) float64; points: (N, 3) float64 -> (N, 2) float64 pixels.
    Points on the principal plane (zero depth) project to inf/nan.
    """
    h = project_homogeneous(P, points)
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[:, :2] / h[:, 2:3]


def project_homogeneous(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Homogeneous pixels ``P @ (X, 1)``: P (3, 4); points (N, 3) -> (N, 3). The third
    coordinate is the depth when P is normalised (:func:`normalize_projection`)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points @ P[:, :3].T + P[:, 3]


def project_per_observation(P_obs: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One camera per point: P_obs (O, 3, 4), points (O, 3) -> (homogeneous (O, 3), pixels (O, 2))."""
    h = np.einsum("oij,oj->oi", P_obs[:, :, :3], points) + P_obs[:, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return h, h[:, :2] / h[:, 2:3]


def camera_center(P: np.ndarray) -> np.ndarray:
    """Camera centre C (3,) with ``P @ (C, 1) = 0``, for a finite camera P (3, 4)."""
    return -np.linalg.solve(P[:, :3], P[:, 3])


def depths(P: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Signed depth of each point in the camera (positive in front), in world units.

    P: (3, 4); points: (N, 3) -> (N,). Invariant to the (signed) scale of P
    (Hartley & Zisserman, eq. 6.15).
    """
    M = P[:, :3]
    w = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ P[2, :3] + P[2, 3]
    return np.sign(np.linalg.det(M)) * w / np.linalg.norm(M[2])


def compose_projection(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """P = K [R | t]. K: (3, 3), R: (3, 3), t: (3,) -> (3, 4)."""
    return K @ np.hstack([R, np.asarray(t, dtype=np.float64).reshape(3, 1)])


def normalize_projection(P: np.ndarray) -> np.ndarray:
    """Scale P so that its left 3x3 block has det > 0 and ||P[2, :3]|| = 1.

    With this scale the third homogeneous coordinate of ``P @ X`` is the depth of X. A
    degenerate P (zero third row, non-finite entries: a failed estimate) gives NaNs, which the
    callers test for; it is not worth a warning.
    """
    M = P[:, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sign(np.linalg.det(M)) / np.linalg.norm(M[2])
        return P * s


def _rq3(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition of a 3x3 matrix: M = U @ Q, U upper triangular, Q orthogonal."""
    flip = np.eye(3)[::-1]
    q, r = np.linalg.qr((flip @ M).T)
    U = flip @ r.T @ flip
    Q = flip @ q.T
    return U, Q


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split P into K, R, t with P ~ K [R | t].

    P: (3, 4) finite camera. Returns K (3, 3) upper triangular with positive diagonal and
    K[2, 2] = 1, R (3, 3) with det R = +1, t (3,). The overall sign of P is chosen so that
    det R = +1 (points in front of the camera then have positive depth).
    """
    P = normalize_projection(np.asarray(P, dtype=np.float64))
    K, R = _rq3(P[:, :3])
    d = np.sign(np.diag(K))
    d[d == 0] = 1.0
    signs = np.diag(d)
    K = K @ signs
    R = signs @ R
    if np.linalg.det(R) < 0:  # cannot happen after normalize_projection, kept for safety
        R = -R
        K = -K
    t = np.linalg.solve(K, P[:, 3])
    scale = K[2, 2]
    return K / scale, R, t


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]_x of a 3-vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def fundamental_from_projections(P1: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """Fundamental matrix F (3, 3), ``x2.T F x1 = 0``, from two finite cameras (3, 4).

    F = [e2]_x P2 P1^+, with e2 = P2 C1 (Hartley & Zisserman, eq. 9.1). Scaled to unit
    Frobenius norm.
    """
    C1 = np.append(camera_center(P1), 1.0)
    e2 = P2 @ C1
    F = skew(e2) @ P2 @ np.linalg.pinv(P1)
    return F / np.linalg.norm(F)


def epipolar_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of each x2 to the epipolar line F x1, and of x1 to F^T x2; the max of both.

    F: (3, 3); x1, x2: (N, 2) -> (N,).
    """
    h1 = to_homogeneous(x1)
    h2 = to_homogeneous(x2)
    l2 = h1 @ F.T  # lines in image 2
    l1 = h2 @ F  # lines in image 1
    num = np.abs(np.sum(h2 * l2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num / np.hypot(l2[:, 0], l2[:, 1])
        d1 = num / np.hypot(l1[:, 0], l1[:, 1])
    return np.maximum(d1, d2)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (degrees) of the relative rotation R_a R_b^T."""
    c = (np.trace(R_a @ R_b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def point_jacobian(P_obs: np.ndarray, h: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """d(u, v)/dX of each observation's projection: P_obs (O, 3, 4), its homogeneous pixels h
    (O, 3) and pixels uv (O, 2) (:func:`project_per_observation`) -> (O, 2, 3)."""
    inv = 1.0 / h[:, 2]
    Ju = (P_obs[:, 0, :3] - uv[:, 0:1] * P_obs[:, 2, :3]) * inv[:, None]
    Jv = (P_obs[:, 1, :3] - uv[:, 1:2] * P_obs[:, 2, :3]) * inv[:, None]
    return np.stack([Ju, Jv], axis=1)


def backproject(P: np.ndarray, pixels: np.ndarray, depth: float) -> np.ndarray:
    """World points (N, 3) at depth ``depth`` (Hartley & Zisserman eq. 6.15, world units) on the
    rays of ``pixels`` (N, 2) of a finite camera P (3, 4), for any sign and scale of P."""
    Pn = normalize_projection(np.asarray(P, dtype=np.float64))
    rays = np.linalg.solve(Pn[:, :3], np.column_stack([pixels, np.ones(len(pixels))]).T).T  # unit depth
    return camera_center(Pn) + depth * rays


def viewing_direction(P: np.ndarray) -> np.ndarray:
    """Unit vector (3,) along the optical axis of camera P (3, 4), towards the scene."""
    return normalize_projection(np.asarray(P, dtype=np.float64))[2, :3]


def intrinsics_turned_180(K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """K (3, 3) of the same camera for its image turned by 180 degrees (``image_size`` =
    (width, height)): pixel (x, y) goes to (W - 1 - x, H - 1 - y), which moves the principal
    point; the focal lengths and skew stay (the roll goes into R)."""
    w, h = image_size
    K = np.array(K, dtype=np.float64)
    K[0, 2], K[1, 2] = w - 1 - K[0, 2], h - 1 - K[1, 2]
    return K
