"""A camera's pose refined from 3D-2D pairs with its intrinsics held, and the covariance of the
refinement: what is left of resection once K is known (Hartley & Zisserman §7.2; OpenCV's
``solvePnPRefineLM`` computes the same pose without its covariance).

The pose is moved by increments about the camera's own axes, as the bundle adjustment moves it
(:func:`stereoseed.geometry.models.projection_derivatives`): R <- exp([w]x) R, t <- t + dt, so
the increment (w, dt) (6,) is in the same parameters as
:func:`stereoseed.estimators.covariance.camera_uncertainty`'s pose block.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereoseed.geometry.models import CameraModel, projection_derivatives, rotation_from_vector, rotation_vector

__all__ = ["PoseRefinement", "refine_pose"]


@dataclass(frozen=True)
class PoseRefinement:
    """increment (6,): (w rad, dt) from the starting pose to the refined one; covariance (6, 6):
    of that increment, sigma^2 (J^T W J)^-1 with sigma the weighted residuals' own; rms_px: the
    refined pose's inlier RMS; n_used: the pairs kept by the robust weights (residual within
    ``inlier_px``); converged: the last step moved the pose by less than 1e-9 of its scale."""

    increment: np.ndarray
    covariance: np.ndarray
    rms_px: float
    n_used: int
    converged: bool


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h = X @ (K @ R).T + K @ t
    return h[:, :2] / h[:, 2:3], h


def _jacobian(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(N, 2, 6) d(pixel)/d(w, dt): the pixel u = h_xy / h_z of h = P X moves with dP X."""
    dP = projection_derivatives(K, R, t, CameraModel.FIXED)  # (6, 3, 4)
    dh = np.einsum("kij,nj->nki", dP[:, :, :3], X) + dP[None, :, :, 3]  # (N, 6, 3)
    z = h[:, 2][:, None]
    du = (dh[:, :, :2] - h[:, None, :2] / z[:, :, None] * dh[:, :, 2:3]) / z[:, :, None]
    return np.swapaxes(du, 1, 2)


def _linearised(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, x: np.ndarray, w_obs: np.ndarray,
                inlier_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """At the pose K [R | t]: (use (N,) the pairs in front within ``inlier_px``, the residuals
    r (N, 2), the weighted normal equations H (6, 6) and gradient g (6,) over ``use``), or None
    with fewer than 6 pairs kept."""
    u, h = _project(K, R, t, X)
    r = u - x
    use = (h[:, 2] > 0) & (np.linalg.norm(r, axis=1) <= inlier_px) & np.isfinite(r).all(axis=1)
    if use.sum() < 6:
        return None
    J = _jacobian(K, R, t, X[use], h[use])
    Jw = J * w_obs[use][:, None, None]
    return use, r, np.einsum("nik,nil->kl", Jw, J), np.einsum("nik,ni->k", Jw, r[use])


def refine_pose(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray, x: np.ndarray,
                weights: np.ndarray | None = None, inlier_px: float = 3.0, iterations: int = 20) -> PoseRefinement | None:
    """Gauss-Newton on the reprojection error of X (N, 3) <-> x (N, 2) over the pose of
    K [R | t] (K (3, 3), R (3, 3), t (3,)), intrinsics held; pairs whose residual exceeds
    ``inlier_px`` at the current pose carry no weight (re-decided at each step: a start within a
    few pixels of the pose, as a camera the walk already placed is); ``weights`` (N,) each pair's share of one independent
    observation (1 by default). None when fewer than 6 pairs are kept or the system is singular."""
    X = np.asarray(X, np.float64)
    x = np.asarray(x, np.float64)
    w_obs = np.ones(len(X)) if weights is None else np.asarray(weights, np.float64)
    R0, t0 = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    Rk, tk = R0.copy(), t0.copy()
    converged = False
    for _ in range(iterations):
        found = _linearised(K, Rk, tk, X, x, w_obs, inlier_px)
        if found is None:
            return None
        _, _, H, g = found
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        Rk = rotation_from_vector(step[:3]) @ Rk
        tk = tk + step[3:]
        if np.linalg.norm(step[3:]) <= 1e-9 * max(np.linalg.norm(tk), 1e-12) and np.linalg.norm(step[:3]) <= 1e-9:
            converged = True
            break
    found = _linearised(K, Rk, tk, X, x, w_obs, inlier_px)  # at the refined pose: its residuals and information
    if found is None:
        return None
    use, r, H, _ = found
    wu = w_obs[use]
    dof = 2.0 * wu.sum() - 6.0
    if dof <= 0:
        return None
    sigma2 = float(np.sum(wu[:, None] * r[use] ** 2) / dof)
    try:
        covariance = sigma2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    # the increment from the starting pose, in the same parameters: R = exp([w]x) R0, t = t0 + dt
    w = rotation_vector(Rk @ R0.T)
    increment = np.concatenate([w, tk - t0])
    return PoseRefinement(increment, covariance, float(np.sqrt(np.mean(np.sum(r[use] ** 2, axis=1)))), int(use.sum()),
                          converged)
