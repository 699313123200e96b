"""Bundle adjustment: Levenberg-Marquardt with the Schur complement on the points.

Paper §4.3 (eq. 12): after each insertion, the newest camera(s) and the points they observe are
refined with older cameras fixed. The same solver runs the windowed local BA of the accurate
mode (Mouragnon et al. 2006) and the global baselines: what changes is which cameras and points
are free. The calibrated pair is always fixed: it carries the metric frame (and the gauge).

The normal equations are [[U, W], [W^T, V]] with V block-diagonal (one 3x3 block per point):
eliminating the points leaves the small reduced camera system S = U - W V^-1 W^T
(Triggs et al. 2000, "Bundle adjustment - a modern synthesis", §6.1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from numba import njit

from stereoseed.geometry import models as camera_models
from stereoseed.geometry.camera import Camera
from stereoseed.estimators.config import BundleConfig
from stereoseed.estimators.robust import huber_cost_of_norms
from stereoseed.estimators._schur import (back_substitute, damped_camera_system, eliminate_points, homogeneous,
                                         normal_equations, solve_symmetric, thread_rows)

__all__ = ["BundleProblem", "BundleResult", "bundle_adjust", "observation_errors", "damped_step", "pairs_by_point"]



@dataclass
class BundleProblem:
    """What a bundle adjustment sees.

    Ps: (C, 3, 4) all cameras involved; free_cameras: (C,) bool; model: the camera model of the
    free cameras (they share one); reference_K: K of the reference camera for the 'focal' model,
    (3, 3), or (C, 3, 3) one per camera (a camera whose image was turned sees the reference
    principal point elsewhere).
    points: (M, 3); free_points: (M,) bool. obs_camera, obs_point: (O,) int indices into Ps and
    points; obs_xy: (O, 2) measured pixels.
    """

    Ps: np.ndarray
    free_cameras: np.ndarray
    points: np.ndarray
    free_points: np.ndarray
    obs_camera: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    model: str = "free"
    reference_K: np.ndarray | None = None
    cameras: list | None = None  # the Camera of each row of Ps (its K, R, t decomposed once), or None


@dataclass
class BundleResult:
    Ps: np.ndarray
    points: np.ndarray
    rms_before: float
    rms_after: float
    iterations: int
    seconds: float
    info: dict = field(default_factory=dict)


def _projection_derivatives(params: np.ndarray, model: str, ref_K: np.ndarray | None) -> np.ndarray:
    """dP/dparam_j of every camera, (C, n, 3, 4) for params (C, n), by central differences (P is
    smooth in its parameters; a relative step of 1e-6 keeps the truncation error near 1e-12).
    ref_K: None, (3, 3), or (C, 3, 3) one per camera."""
    C, n = params.shape
    step = 1e-6 * np.maximum(1.0, np.abs(params))  # (C, n)
    shifts = step[:, :, None] * np.eye(n)  # camera c's parameter j moved: row (c, j)
    refs = ref_K if ref_K is None or ref_K.ndim == 2 else np.repeat(ref_K, n, axis=0)
    plus = camera_models.projections_from_params((params[:, None, :] + shifts).reshape(C * n, n), model, refs)
    minus = camera_models.projections_from_params((params[:, None, :] - shifts).reshape(C * n, n), model, refs)
    return (plus - minus).reshape(C, n, 3, 4) / (2 * step)[:, :, None, None]


def observation_errors(Ps: np.ndarray, points: np.ndarray, obs_camera: np.ndarray, obs_point: np.ndarray,
                       obs_xy: np.ndarray) -> np.ndarray:
    """Reprojection distance (O,) px of each observation: camera obs_camera (O,) of Ps (C, 3, 4)
    seeing point obs_point (O,) of points (M, 3) at pixel obs_xy (O, 2); NaN or inf for a point
    at infinity or a NaN camera. One compiled pass, without the (O, 3, 4) array of gathered
    cameras that :func:`stereoseed.geometry.projection.project_per_observation` needs: the LM judges every
    trial step by it, and the mapper drops outliers by it after every insertion."""
    out = np.empty(len(obs_camera))
    _observation_errors(np.ascontiguousarray(Ps, np.float64), np.ascontiguousarray(points, np.float64),
                        np.ascontiguousarray(obs_camera, np.int64), np.ascontiguousarray(obs_point, np.int64),
                        np.ascontiguousarray(obs_xy, np.float64), out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")  # a zero depth divides to inf, not an exception
def _observation_errors(Ps, X, oc, op, xy, out):
    for o in range(oc.shape[0]):
        h0, h1, h2 = homogeneous(Ps, oc[o], X[op[o], 0], X[op[o], 1], X[op[o], 2])
        ru, rv = h0 / h2 - xy[o, 0], h1 / h2 - xy[o, 1]
        out[o] = np.sqrt(ru * ru + rv * rv)


def pairs_by_point(points: np.ndarray, cameras: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (point, camera) pairs of W's rows (points (K,), cameras (K,)) grouped by point, then by
    camera within a point, as the reduced camera system's kernel adds them: (order (K,), starts:
    each point's first position in order, and K at the end)."""
    order = np.lexsort((cameras, points))
    grouped = points[order]
    starts = np.flatnonzero(np.r_[True, grouped[1:] != grouped[:-1], True]) if len(grouped) else np.zeros(1, np.int64)
    return order, starts


def damped_step(trial: Callable[[float], tuple[Any, float]], cost: float, lam: float
                ) -> tuple[Any, float, float, float]:
    """One Levenberg-Marquardt iteration's damping: ``trial(lam)`` (the state a step damped by lam
    reaches, its cost) with lam raised tenfold until the cost falls (lam then lowered to 0.3x, at
    least 1e-9) or lam passes 1e8. Returns (the new state, or None when no step lowered the
    cost; its cost; the next lam; the relative improvement, 0 without one)."""
    while True:
        state, new_cost = trial(lam)
        if np.isfinite(new_cost) and new_cost < cost:
            return state, new_cost, max(lam * 0.3, 1e-9), (cost - new_cost) / max(cost, 1e-300)
        lam *= 10.0
        if lam > 1e8:
            return None, cost, lam, 0.0


def bundle_adjust(problem: BundleProblem, config: BundleConfig = BundleConfig()) -> BundleResult:
    """Minimise the robust reprojection error over the free cameras and free points.

    Returns new cameras (C, 3, 4) and points (M, 3); fixed ones are returned unchanged.
    Observations of fixed points by free cameras pin those cameras (paper.md §4 trap).
    """
    t0 = time.perf_counter()
    Ps = np.array(problem.Ps, dtype=np.float64, copy=True)
    X = np.array(problem.points, dtype=np.float64, copy=True)
    oc = np.asarray(problem.obs_camera, dtype=np.int64)
    op = np.asarray(problem.obs_point, dtype=np.int64)
    xy = np.asarray(problem.obs_xy, dtype=np.float64)
    free_cams = np.flatnonzero(problem.free_cameras)
    free_pts = np.asarray(problem.free_points, dtype=bool)
    model = problem.model
    ref_Ks = None if problem.reference_K is None else np.asarray(problem.reference_K, np.float64)

    def ref_K(c: int) -> np.ndarray | None:
        return ref_Ks if ref_Ks is None or ref_Ks.ndim == 2 else ref_Ks[c]

    delta = config.huber_px

    all_oc, all_op, all_xy = oc, op, xy

    def rms(Ps_: np.ndarray, X_: np.ndarray) -> float:
        return float(np.sqrt(np.mean(observation_errors(Ps_, X_, all_oc, all_op, all_xy) ** 2))) if len(all_oc) else 0.0

    rms_before = rms(Ps, X)
    # Only observations touching something free matter; the others add a constant.
    relevant = np.isin(oc, free_cams) | free_pts[op]
    oc, op, xy = oc[relevant], op[relevant], xy[relevant]
    if len(oc) == 0 or (len(free_cams) == 0 and not free_pts.any()):
        return BundleResult(Ps, X, rms_before, rms_before, 0, time.perf_counter() - t0)

    n = camera_models.n_params(model) if len(free_cams) else 0
    cam_slot = np.full(len(Ps), -1, dtype=np.int64)
    cam_slot[free_cams] = np.arange(len(free_cams))
    # a camera's decomposition comes from its Camera, made once per camera value (not per BA)
    cams = problem.cameras if problem.cameras is not None else [Camera(P) for P in Ps]
    params = np.array([camera_models.params_from_decomposition(*cams[c].krt, model, ref_K(c)) for c in free_cams]
                      ).reshape(len(free_cams), n)
    free_ref_K = ref_Ks if ref_Ks is None or ref_Ks.ndim == 2 else ref_Ks[free_cams]
    if len(free_cams):  # start from the model's closest camera
        Ps[free_cams] = camera_models.projections_from_params(params, model, free_ref_K)
    free_pt_idx = np.flatnonzero(free_pts)
    pt_slot = np.full(len(X), -1, dtype=np.int64)
    pt_slot[free_pt_idx] = np.arange(len(free_pt_idx))
    slot_c = cam_slot[oc]
    slot_p = pt_slot[op]
    has_c = slot_c >= 0
    has_p = slot_p >= 0
    both = has_c & has_p
    nC, nP = len(free_cams), len(free_pt_idx)

    # the observations of a free point by a free camera: the rows of W
    both_idx_all = np.flatnonzero(both)
    both_row = np.full(len(oc), -1, np.int64)  # observation -> its row of W
    both_row[both_idx_all] = np.arange(len(both_idx_all))
    both_point, both_camera = slot_p[both_idx_all], slot_c[both_idx_all]
    # grouped by point, then by camera within a point: the pairs that make the reduced system
    pair_order, point_starts = pairs_by_point(both_point, both_camera)
    rows = thread_rows(pair_order, point_starts, both_camera, nC)

    whole = np.ones(len(oc))  # every observation is one (the covariance weighs correlated ones less)
    lam = 1e-3
    cost = huber_cost_of_norms(observation_errors(Ps, X, oc, op, xy), delta)
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        dP = _projection_derivatives(params, model, free_ref_K) if nC else np.zeros((0, n, 3, 4))
        U, gc, V, gp, Wb = normal_equations(Ps, X, oc, op, xy, whole, cam_slot, pt_slot, dP, float(delta), both_row,
                                            nC, nP, len(both_idx_all))

        Wt = np.swapaxes(Wb, 1, 2).copy()  # rows of W^T: contiguous for the reduced system's kernel
        def trial(lam: float) -> tuple[tuple, float]:  # called at once by damped_step, in this iteration
            Vinv, Y, rhs = eliminate_points(V, gp, gc, Wb, lam, both_point, both_camera)
            if nC:
                S2 = damped_camera_system(pair_order, point_starts, both_camera, Wt, Y, U, lam, rows)
                dc = solve_symmetric(S2, rhs.ravel()).reshape(nC, n)
            else:
                dc = np.zeros((0, n))
            dp = back_substitute(Vinv, gp, Wb, dc, both_point, both_camera)
            new_params = params + dc
            Ps_new = Ps.copy()
            if nC:
                Ps_new[free_cams] = camera_models.projections_from_params(new_params, model, free_ref_K)
            X_new = X.copy()
            X_new[free_pt_idx] += dp
            with np.errstate(all="ignore"):  # a trial step may put a point at infinity: refused below
                return (new_params, Ps_new, X_new), huber_cost_of_norms(observation_errors(Ps_new, X_new, oc, op, xy),
                                                                        delta)

        step, cost, lam, improvement = damped_step(trial, cost, lam)
        if step is not None:
            params, Ps, X = step
        if improvement < 1e-6:
            break

    rms_after = rms(Ps, X)
    return BundleResult(Ps, X, rms_before, rms_after, iterations, time.perf_counter() - t0,
                        info={"free_cameras": int(nC), "free_points": int(nP), "observations": int(len(oc))})
