"""Camera calibration from a 3D pattern: normalised DLT, then maximum-likelihood refinement.

Paper §4.1 step 1: each camera of the stereo pair is calibrated from the known 3D points of a
pattern and their pixels. The same DLT estimates the moving camera later (``resection``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereoseed.geometry.camera import Camera
from stereoseed.geometry import models as camera_models
from stereoseed.estimators._calibration_kernels import refine_camera
from stereoseed.geometry.projection import depths, normalize_projection, project
from stereoseed.errors import StereoseedError

__all__ = [
    "normalization_2d",
    "normalization_3d",
    "check_correspondences",
    "dlt_projection",
    "refine_projection",
    "reprojection_rms",
    "CalibrationResult",
    "calibrate_camera",
]

MIN_POINTS = 6  # 11 DOF, two equations per point (paper eq. 10-11)


def normalization_2d(points: np.ndarray) -> np.ndarray:
    """Hartley similarity T (3, 3): centroid to 0, mean distance sqrt(2). points: (N, 2)."""
    c = points.mean(axis=0)
    d = np.mean(np.linalg.norm(points - c, axis=1))
    s = np.sqrt(2.0) / max(d, 1e-12)
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def normalization_3d(points: np.ndarray) -> np.ndarray:
    """Hartley similarity U (4, 4): centroid to 0, mean distance sqrt(3). points: (N, 3)."""
    c = points.mean(axis=0)
    d = np.mean(np.linalg.norm(points - c, axis=1))
    s = np.sqrt(3.0) / max(d, 1e-12)
    U = np.eye(4) * s
    U[:3, 3] = -s * c
    U[3, 3] = 1.0
    return U


def check_correspondences(points3d: np.ndarray, points2d: np.ndarray, coplanarity_tol: float = 1e-3,
                          what: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """Validate 3D-2D pairs for a DLT; raise :class:`StereoseedError` with a clear reason.

    points3d: (N, 3), points2d: (N, 2). Refuses fewer than 6 pairs, non-finite values and 3D
    points that are (nearly) coplanar or collinear: the smallest singular value of the centred,
    normalised point cloud relative to the largest must exceed ``coplanarity_tol``.
    """
    X = np.asarray(points3d, dtype=np.float64)
    x = np.asarray(points2d, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise StereoseedError(f"{what}: 3D points must have shape (N, 3), got {X.shape}")
    if x.ndim != 2 or x.shape[1] != 2:
        raise StereoseedError(f"{what}: image points must have shape (N, 2), got {x.shape}")
    if len(X) != len(x):
        raise StereoseedError(f"{what}: {len(X)} 3D points but {len(x)} image points; give one pixel per 3D point")
    if len(X) < MIN_POINTS:
        raise StereoseedError(f"{what}: {len(X)} correspondences, at least {MIN_POINTS} are needed for a DLT")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(x))):
        raise StereoseedError(f"{what}: NaN or infinite coordinates; remove or fix those lines")
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if sv[0] <= 0 or sv[2] / sv[0] < coplanarity_tol:
        raise StereoseedError(
            f"{what}: the 3D points are (nearly) coplanar; a DLT needs a non-planar pattern "
            "(e.g. two faces of a box)")
    return X, x


def dlt_projection(points3d: np.ndarray, points2d: np.ndarray) -> np.ndarray:
    """Linear (DLT) estimate of P from N >= 6 3D-2D pairs with Hartley normalisation.

    points3d: (N, 3), points2d: (N, 2) -> P (3, 4), scaled by :func:`normalize_projection`.
    Solves the 2N x 12 system of paper eq. 10-11 by SVD (HZ algorithm 7.1).
    """
    X = np.asarray(points3d, dtype=np.float64)
    x = np.asarray(points2d, dtype=np.float64)
    T = normalization_2d(x)
    U = normalization_3d(X)
    Xn = np.hstack([X, np.ones((len(X), 1))]) @ U.T
    xn = np.hstack([x, np.ones((len(x), 1))]) @ T.T
    n = len(X)
    A = np.zeros((2 * n, 12))
    A[0::2, 4:8] = -Xn
    A[0::2, 8:12] = xn[:, 1:2] * Xn
    A[1::2, 0:4] = Xn
    A[1::2, 8:12] = -xn[:, 0:1] * Xn
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Pn = Vt[-1].reshape(3, 4)
    P = np.linalg.solve(T, Pn @ U)
    return normalize_projection(P)


def reprojection_rms(P: np.ndarray, points3d: np.ndarray, points2d: np.ndarray) -> float:
    """RMS (px) over points of the reprojection distance. P: (3, 4); (N, 3); (N, 2)."""
    r = project(P, points3d) - points2d
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def refine_projection(P: np.ndarray, points3d: np.ndarray, points2d: np.ndarray,
                      model: str = "free", reference_K: np.ndarray | None = None,
                      loss: str = "linear", f_scale: float = 1.0, max_iterations: int = 100) -> np.ndarray:
    """Levenberg-Marquardt refinement of P minimising the reprojection error (ML under
    Gaussian pixel noise).

    P: (3, 4) initial camera; points3d: (N, 3); points2d: (N, 2). ``model`` is a camera model of
    :mod:`stereoseed.geometry.models` ("free": 11 DOF K+R+t). ``loss`` "huber" with ``f_scale``
    px makes it robust (on each point's 2D error, as the bundle adjustment does; solved by
    iteratively reweighted least squares). Returns the refined P (3, 4).

    The Jacobian is analytic (the derivatives of ``camera_models.projection_derivatives``
    chained through the projection) and the loop compiled
    (:func:`stereoseed.estimators._calibration_kernels.refine_camera`): resection polishes hundreds of
    hypotheses in a run.
    """
    if loss not in ("linear", "huber"):
        raise ValueError(f"loss must be 'linear' or 'huber', not {loss!r}")
    params, fixed = camera_models.params_from_projection(P, model, reference_K)
    _, R, t = camera_models.krt_from_params(params, model, fixed)
    intrinsics = params[:camera_models.N_INTRINSICS[model]]
    K_base, dK = camera_models.linear_K(intrinsics, model, fixed)
    X = np.ascontiguousarray(points3d, dtype=np.float64).reshape(-1, 3)
    x = np.ascontiguousarray(points2d, dtype=np.float64).reshape(-1, 2)
    delta = float(f_scale) if loss == "huber" else np.inf
    return normalize_projection(refine_camera(K_base, dK, np.ascontiguousarray(intrinsics, np.float64), R,
                                              np.ascontiguousarray(t, np.float64), X, x, delta, int(max_iterations)))


@dataclass
class CalibrationResult:
    """A calibrated camera: P (3, 4), its K, R, t and the reprojection RMS over the pattern (px)."""

    P: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rms_px: float
    n_points: int

    def to_dict(self) -> dict:
        return {"P": self.P.tolist(), "K": self.K.tolist(), "R": self.R.tolist(),
                "t": self.t.tolist(), "rms_px": self.rms_px, "n_points": self.n_points}


# A calibration is refused when it cannot be a camera looking at its pattern: pixels typed or
# detected with care reproject within a few pixels (mismatched or reordered points: ~100 px), a
# pattern lies in front of the camera (swapped u and v mirror it behind), and a physical camera's
# pixels are nearly square and unskewed.
MAX_CALIBRATION_RMS_PX = 5.0
MAX_ASPECT_CHANGE = 0.2  # |fy / fx - 1|
MAX_SKEW = 0.05  # |K[0, 1] / fx|


def calibrate_camera(pattern: np.ndarray, pixels: np.ndarray, what: str = "calibration") -> CalibrationResult:
    """Calibrate one camera from a non-planar pattern: normalised DLT, then LM on all 11 DOF.

    pattern: (N, 3) known 3D points (N >= 6, not coplanar); pixels: (N, 2) their image points.
    Raises :class:`StereoseedError` when the result cannot be the camera that saw the pattern
    (reprojection RMS above ``MAX_CALIBRATION_RMS_PX``, pattern points behind it, absurd pixels).
    """
    X, x = check_correspondences(pattern, pixels, what=what)
    P = refine_projection(dlt_projection(X, x), X, x, model="free")
    K, R, t = Camera(P).krt
    result = CalibrationResult(P=P, K=K, R=R, t=t, rms_px=reprojection_rms(P, X, x), n_points=len(X))
    behind = float(np.mean(depths(P, X) <= 0))
    if result.rms_px > MAX_CALIBRATION_RMS_PX:
        raise StereoseedError(f"{what}: the pattern points reproject with {result.rms_px:.1f} px RMS (limit "
                              f"{MAX_CALIBRATION_RMS_PX:g} px); are the pixels in the same order as the pattern points?")
    if behind > 0:
        raise StereoseedError(f"{what}: {100 * behind:.0f} % of the pattern points would be behind the camera; "
                              f"are u and v swapped, or the pattern's axes mirrored?")
    aspect, skew = K[1, 1] / K[0, 0] - 1.0, K[0, 1] / K[0, 0]
    if abs(aspect) > MAX_ASPECT_CHANGE or abs(skew) > MAX_SKEW:
        raise StereoseedError(f"{what}: the camera's pixels come out {100 * aspect:+.0f} % taller than wide with skew "
                              f"{skew:+.2f}; no camera is like that: check the pattern's coordinates and the pixels")
    return result
