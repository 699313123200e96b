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

import numpy as np
from numba import njit

from . import camera_models
from .camera import camera_jacobian, point_jacobian, project_per_observation
from .config import BundleConfig
from .robust import huber_cost, huber_weights

__all__ = ["BundleProblem", "BundleResult", "bundle_adjust"]


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
    """dP/dparam_j for one camera, (n, 3, 4), by central differences (P is smooth in its
    parameters; a relative step of 1e-6 keeps the truncation error near 1e-12)."""
    n = len(params)
    out = np.empty((n, 3, 4))
    for j in range(n):
        step = 1e-6 * max(1.0, abs(params[j]))
        p_plus = params.copy()
        p_plus[j] += step
        p_minus = params.copy()
        p_minus[j] -= step
        out[j] = (camera_models.projection_from_params(p_plus, model, ref_K)
                  - camera_models.projection_from_params(p_minus, model, ref_K)) / (2 * step)
    return out


class _Segments:
    """Sums of per-observation values grouped by an integer key (0..n-1), with the grouping
    (a stable sort) computed once: ``np.add.reduceat`` is far faster than ``np.add.at``."""

    def __init__(self, keys: np.ndarray, n: int):
        self.n = n
        self.order = np.argsort(keys, kind="stable")
        sorted_keys = keys[self.order]
        self.starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]]) if len(keys) else np.zeros(0, int)
        self.keys = sorted_keys[self.starts] if len(keys) else np.zeros(0, int)

    def groups(self):
        """(key, the positions (K,) of its values in the grouped array), key by key."""
        ends = np.r_[self.starts[1:], len(self.order)]
        for key, start, end in zip(self.keys, self.starts, ends):
            yield int(key), self.order[start:end]

    def sum(self, values: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n,) + values.shape[1:])
        if len(self.keys):
            out[self.keys] = np.add.reduceat(values[self.order], self.starts, axis=0)
        return out


@njit(cache=True, nogil=True)
def _reduced_camera_matrix(order, starts, cams, W, Y, n_cams):
    """-W V^-1 W^T of the reduced camera system, camera-major (n_cams n, n_cams n): every pair of
    observations (i, j) of one point adds -Y_i W_j^T (n, n) at cameras (cams[i], cams[j]).
    order: observations grouped by point, starts: (groups + 1,) offsets of the groups into it;
    W, Y: (O, n, 3) with Y_i = W_i V_p^-1."""
    n = W.shape[1]
    S = np.zeros((n_cams * n, n_cams * n))
    for p in range(len(starts) - 1):
        for a in range(starts[p], starts[p + 1]):
            i = order[a]
            ri = cams[i] * n
            for b in range(a, starts[p + 1]):  # Y_j W_i^T = (Y_i W_j^T)^T: each pair once
                j = order[b]
                rj = cams[j] * n
                for u in range(n):
                    for v in range(n):
                        x = Y[i, u, 0] * W[j, v, 0] + Y[i, u, 1] * W[j, v, 1] + Y[i, u, 2] * W[j, v, 2]
                        S[ri + u, rj + v] -= x
                        if b != a:
                            S[rj + v, ri + u] -= x
    return S


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

    def residuals(Ps_: np.ndarray, X_: np.ndarray) -> np.ndarray:
        return project_per_observation(Ps_[all_oc], X_[all_op])[1] - all_xy

    r = residuals(Ps, X)
    rms_before = float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else 0.0
    # Only observations touching something free matter; the others add a constant.
    relevant = np.isin(oc, free_cams) | free_pts[op]
    oc, op, xy = oc[relevant], op[relevant], xy[relevant]
    if len(oc) == 0 or (len(free_cams) == 0 and not free_pts.any()):
        return BundleResult(Ps, X, rms_before, rms_before, 0, time.perf_counter() - t0)

    n = camera_models.n_params(model) if len(free_cams) else 0
    cam_slot = np.full(len(Ps), -1, dtype=np.int64)
    cam_slot[free_cams] = np.arange(len(free_cams))
    params = [camera_models.params_from_projection(Ps[c], model, ref_K(c))[0] for c in free_cams]
    for c, p in zip(free_cams, params):  # start from the model's closest camera
        Ps[c] = camera_models.projection_from_params(p, model, ref_K(c))
    free_pt_idx = np.flatnonzero(free_pts)
    pt_slot = np.full(len(X), -1, dtype=np.int64)
    pt_slot[free_pt_idx] = np.arange(len(free_pt_idx))
    slot_c = cam_slot[oc]
    slot_p = pt_slot[op]
    has_c = slot_c >= 0
    has_p = slot_p >= 0
    both = has_c & has_p
    nC, nP = len(free_cams), len(free_pt_idx)

    # sums over observations grouped by point / by camera, precomputed once
    by_point = _Segments(slot_p[has_p], nP)
    by_camera = _Segments(slot_c[has_c], nC)
    rows_of_free_cameras = np.flatnonzero(has_c)
    both_idx_all = np.flatnonzero(both)
    both_by_camera = _Segments(slot_c[both], nC)
    by_point_both = _Segments(slot_p[both_idx_all], nP)
    # the same grouping (observations of free points by free cameras, point by point) sums S's
    # off-diagonal blocks
    point_starts = np.r_[by_point_both.starts, len(both_idx_all)]
    eye_n, eye_3 = np.eye(n), np.eye(3)

    lam = 1e-3
    cost = huber_cost(project_per_observation(Ps[oc], X[op])[1] - xy, delta)
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        h, uv = project_per_observation(Ps[oc], X[op])
        r = uv - xy
        w = huber_weights(r, delta)
        Jp = point_jacobian(Ps[oc], h, uv)  # (O, 2, 3)
        Jc = np.zeros((len(oc), 2, n))
        Xh = np.hstack([X[op], np.ones((len(op), 1))])
        for slot, positions in by_camera.groups():  # one sort, not a scan of all observations per camera
            sel = rows_of_free_cameras[positions]
            dP = _projection_derivatives(params[slot], model, ref_K(free_cams[slot]))
            Jc[sel] = camera_jacobian(dP, Xh[sel], h[sel], uv[sel])
        wJcT = np.swapaxes(Jc, 1, 2) * w[:, None, None]  # (O, n, 2)
        wJpT = np.swapaxes(Jp, 1, 2) * w[:, None, None]  # (O, 3, 2)
        U = by_camera.sum((wJcT @ Jc)[has_c])
        gc = by_camera.sum((wJcT @ r[:, :, None])[has_c, :, 0])
        V = by_point.sum((wJpT @ Jp)[has_p])
        gp = by_point.sum((wJpT @ r[:, :, None])[has_p, :, 0])
        Wo = wJcT @ Jp  # (O, n, 3), meaningful where both

        while True:
            Ud = U + lam * (U * eye_n) + 1e-12 * eye_n
            Vd = V + lam * (V * eye_3) + 1e-12 * eye_3
            Vinv = np.linalg.inv(Vd)
            if nC:
                Wb = Wo[both_idx_all]
                Y = Wb @ Vinv[slot_p[both_idx_all]]  # (Ob, n, 3)
                S2 = _reduced_camera_matrix(by_point_both.order, point_starts, slot_c[both_idx_all], Wb, Y, nC)
                for i in range(nC):
                    S2[i * n:(i + 1) * n, i * n:(i + 1) * n] += Ud[i]
                rhs = -gc + both_by_camera.sum((Y @ gp[slot_p[both_idx_all]][:, :, None])[:, :, 0])
                try:
                    dc = np.linalg.solve(S2, rhs.ravel()).reshape(nC, n)
                except np.linalg.LinAlgError:
                    dc = np.linalg.lstsq(S2, rhs.ravel(), rcond=None)[0].reshape(nC, n)
                # back-substitution: V dp = -gp - W^T dc
                back = -gp - by_point_both.sum((np.swapaxes(Wb, 1, 2) @ dc[slot_c[both_idx_all]][:, :, None])[:, :, 0])
            else:
                dc = np.zeros((0, n))
                back = -gp
            dp = (Vinv @ back[:, :, None])[:, :, 0]

            new_params = [params[i] + dc[i] for i in range(nC)]
            Ps_new = Ps.copy()
            for i, c in enumerate(free_cams):
                Ps_new[c] = camera_models.projection_from_params(new_params[i], model, ref_K(c))
            X_new = X.copy()
            X_new[free_pt_idx] += dp
            with np.errstate(all="ignore"):
                new_cost = huber_cost(project_per_observation(Ps_new[oc], X_new[op])[1] - xy, delta)
            if np.isfinite(new_cost) and new_cost < cost:
                improvement = (cost - new_cost) / max(cost, 1e-300)
                params, Ps, X, cost = new_params, Ps_new, X_new, new_cost
                lam = max(lam * 0.3, 1e-9)
                break
            lam *= 10.0
            if lam > 1e8:
                improvement = 0.0
                break
        if improvement < 1e-6:
            break

    r = residuals(Ps, X)
    rms_after = float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else 0.0
    return BundleResult(Ps, X, rms_before, rms_after, iterations, time.perf_counter() - t0,
                        info={"free_cameras": int(nC), "free_points": int(nP), "observations": int(len(oc))})
