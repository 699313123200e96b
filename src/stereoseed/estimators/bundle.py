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
from stereoseed.threads import current_chunks, map_chunks

__all__ = ["BundleProblem", "BundleResult", "bundle_adjust", "observation_errors", "damped_step", "pairs_by_point"]

# Threads forming the reduced camera system: the cores this process may use (threads.py), at
# most 4 (the loop is memory-bound beyond that); below PAIRS_PER_THREAD observation pairs a
# thread costs more than it saves (a pair is ~10 ns, a thread's start ~50 us).
_MAX_THREADS = 4
PAIRS_PER_THREAD = 20_000


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


def _solve_symmetric(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x of S x = rhs for the damped reduced camera system S (N, N), symmetric positive definite:
    by Cholesky (half the work of LU), least squares should damping not have made it definite."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve  # only where cameras are adjusted

    if not np.isfinite(S).all():  # from a singular point block: no step (the cost refuses NaN)
        return np.full(len(rhs), np.nan)
    try:
        return cho_solve(cho_factor(S, check_finite=False), rhs, check_finite=False)
    except (LinAlgError, ValueError):
        return np.linalg.lstsq(S, rhs, rcond=None)[0]


@njit(cache=True, nogil=True)
def _eliminate_points(V, gp, gc, W, lam, point, camera):
    """The points' side of the Schur complement under Levenberg-Marquardt damping ``lam``:
    Vinv (P, 3, 3) the inverses of the damped point blocks (diagonal times 1 + lam, plus 1e-12;
    by cofactors), Y (O, n, 3) = W V^-1 per observation, and the reduced right-hand side
    rhs (C, n) = -gc + sum Y gp. V (P, 3, 3), gp (P, 3), gc (C, n), W (O, n, 3); point, camera
    (O,) the free slots of each observation of a free point by a free camera."""
    n_points = V.shape[0]
    Vinv = np.empty((n_points, 3, 3))
    for p in range(n_points):
        a = V[p].copy()
        for k in range(3):
            a[k, k] = a[k, k] * (1.0 + lam) + 1e-12
        c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
        c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
        c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
        det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
        inv_det = 1.0 / det if det != 0.0 else np.inf  # a singular block: a step the cost refuses
        Vinv[p, 0, 0] = c00 * inv_det
        Vinv[p, 1, 0] = c01 * inv_det
        Vinv[p, 2, 0] = c02 * inv_det
        Vinv[p, 0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) * inv_det
        Vinv[p, 1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * inv_det
        Vinv[p, 2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * inv_det
        Vinv[p, 0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) * inv_det
        Vinv[p, 1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * inv_det
        Vinv[p, 2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * inv_det
    n = W.shape[1]
    Y = np.empty((W.shape[0], n, 3))
    rhs = -gc
    for o in range(W.shape[0]):
        p, c = point[o], camera[o]
        for u in range(n):
            for k in range(3):
                Y[o, u, k] = W[o, u, 0] * Vinv[p, 0, k] + W[o, u, 1] * Vinv[p, 1, k] + W[o, u, 2] * Vinv[p, 2, k]
            rhs[c, u] += Y[o, u, 0] * gp[p, 0] + Y[o, u, 1] * gp[p, 1] + Y[o, u, 2] * gp[p, 2]
    return Vinv, Y, rhs


@njit(cache=True, nogil=True)
def _back_substitute(Vinv, gp, W, dc, point, camera):
    """The points' step dp (P, 3) = V^-1 (-gp - sum W^T dc) once the cameras' step dc (C, n) is
    known (arguments as :func:`_eliminate_points`)."""
    back = -gp
    n = W.shape[1]
    for o in range(W.shape[0]):
        p, c = point[o], camera[o]
        for k in range(3):
            acc = 0.0
            for u in range(n):
                acc += W[o, u, k] * dc[c, u]
            back[p, k] -= acc
    dp = np.empty_like(back)
    for p in range(back.shape[0]):
        for k in range(3):
            dp[p, k] = Vinv[p, k, 0] * back[p, 0] + Vinv[p, k, 1] * back[p, 1] + Vinv[p, k, 2] * back[p, 2]
    return dp


@njit(cache=True, nogil=True)
def _add_point_pairs(S, order, starts, cams, Wt, Y, first_cam, end_cam):
    """Adds -Y_i W_j^T (n, n) to S at cameras (cams[i], cams[j]) for every pair of observations
    (i, j) of one point whose first camera is in [first_cam, end_cam): the rows of S a thread
    owns. order: observations grouped by point and, within a point, by camera; starts:
    (groups + 1,) offsets of the groups into it; Wt: (O, 3, n) the W blocks transposed,
    Y: (O, n, 3) with Y_i = W_i V_p^-1. S is symmetric: each pair is added once, to the upper
    block triangle (cams[i] <= cams[j] by the order), along rows of S and of Wt (contiguous,
    so the innermost loop is vectorised); :func:`_mirror_upper` completes it."""
    n = Wt.shape[2]
    for p in range(len(starts) - 1):
        for a in range(starts[p], starts[p + 1]):
            i = order[a]
            if cams[i] < first_cam or cams[i] >= end_cam:
                continue
            ri = cams[i] * n
            y = Y[i]
            for b in range(a, starts[p + 1]):
                j = order[b]
                rj = cams[j] * n
                w = Wt[j]
                for u in range(n):
                    y0, y1, y2 = y[u, 0], y[u, 1], y[u, 2]
                    row = S[ri + u, rj:rj + n]
                    for v in range(n):
                        row[v] -= y0 * w[0, v] + y1 * w[1, v] + y2 * w[2, v]
                    if b != a and ri == rj:  # a point seen twice by one camera: both halves of its block
                        for v in range(n):
                            S[rj + v, ri + u] -= y0 * w[0, v] + y1 * w[1, v] + y2 * w[2, v]


@njit(cache=True, nogil=True)
def _mirror_upper(S, n):
    """Below the (n, n) diagonal blocks of S, the mirror of what is above them."""
    size = S.shape[0]
    for r in range(size):
        for c in range(r - r % n + n, size):
            S[c, r] = S[r, c]


def _thread_rows(order: np.ndarray, starts: np.ndarray, cams: np.ndarray, n_cams: int) -> np.ndarray:
    """How :func:`_reduced_camera_matrix` shares its block rows among threads: (T + 1,) camera
    bounds, thread t owning cameras [bounds[t], bounds[t + 1]), split so that each adds as many
    observation pairs (one thread below ``PAIRS_PER_THREAD`` pairs). Arguments as
    :func:`_add_point_pairs`; the layout is the BA's, fixed over its iterations."""
    group_end = np.repeat(starts[1:], np.diff(starts))
    pairs = np.bincount(cams[order], weights=group_end - np.arange(len(order)), minlength=n_cams)  # per first camera
    threads = int(max(1, min(_MAX_THREADS, current_chunks(), pairs.sum() // PAIRS_PER_THREAD)))
    cuts = np.searchsorted(np.cumsum(pairs), pairs.sum() * np.arange(1, threads) / threads)
    return np.r_[0, cuts + 1, n_cams].astype(np.int64)


def damped_camera_system(order: np.ndarray, starts: np.ndarray, cams: np.ndarray, Wt: np.ndarray, Y: np.ndarray,
                         U: np.ndarray, lam: float, rows: np.ndarray) -> np.ndarray:
    """The reduced camera system under Levenberg-Marquardt damping ``lam``: U - W V^-1 W^T with
    each camera's diagonal block U (C, n, n) scaled by 1 + lam (plus 1e-12), camera-major
    (C n, C n). Arguments as :func:`_reduced_camera_matrix`."""
    n_cams, n = U.shape[0], U.shape[1]
    eye = np.eye(n)
    S = _reduced_camera_matrix(order, starts, cams, Wt, Y, n_cams, rows)
    Ud = U + lam * (U * eye) + 1e-12 * eye
    for i in range(n_cams):
        S[i * n:(i + 1) * n, i * n:(i + 1) * n] += Ud[i]
    return S


def _reduced_camera_matrix(order: np.ndarray, starts: np.ndarray, cams: np.ndarray, Wt: np.ndarray, Y: np.ndarray,
                           n_cams: int, rows: np.ndarray) -> np.ndarray:
    """-W V^-1 W^T of the reduced camera system, camera-major (n_cams n, n_cams n). Forming it
    costs the sum over points of (track length)^2 blocks: its block rows are shared among the
    threads of ``rows`` (:func:`_thread_rows`; the kernel releases the GIL)."""
    n = Wt.shape[2]
    S = np.zeros((n_cams * n, n_cams * n))
    map_chunks(lambda first, end: _add_point_pairs(S, order, starts, cams, Wt, Y, first, end), rows)
    _mirror_upper(S, n)
    return S


@njit(cache=True, nogil=True, inline="always")
def _homogeneous(Ps, c, x0, x1, x2):
    """Ps[c] @ (x0, x1, x2, 1): the homogeneous pixel of a point in camera c of Ps (C, 3, 4)."""
    return (Ps[c, 0, 0] * x0 + Ps[c, 0, 1] * x1 + Ps[c, 0, 2] * x2 + Ps[c, 0, 3],
            Ps[c, 1, 0] * x0 + Ps[c, 1, 1] * x1 + Ps[c, 1, 2] * x2 + Ps[c, 1, 3],
            Ps[c, 2, 0] * x0 + Ps[c, 2, 1] * x1 + Ps[c, 2, 2] * x2 + Ps[c, 2, 3])


@njit(cache=True, nogil=True)
def _normal_equations(Ps, X, oc, op, xy, cam_slot, pt_slot, dP, delta, both_row, n_cams, n_points, n_both):
    """The Gauss-Newton blocks of the robust (Huber, IRLS) reprojection error, one pass over the
    observations with nothing stored per observation but W: U (n_cams, n, n) and gc (n_cams, n)
    of the free cameras, V (n_points, 3, 3) and gp (n_points, 3) of the free points, and
    W (n_both, n, 3) = w Jc^T Jp of each observation of a free point by a free camera (its row
    ``both_row[o]``). Ps (C, 3, 4), X (M, 3); oc, op (O,) observation -> camera, point;
    xy (O, 2); cam_slot (C,), pt_slot (M,) the free index or -1; dP (n_cams, n, 3, 4) dP/dparams
    of each free camera."""
    n = dP.shape[1]
    U = np.zeros((n_cams, n, n))
    gc = np.zeros((n_cams, n))
    V = np.zeros((n_points, 3, 3))
    gp = np.zeros((n_points, 3))
    W = np.zeros((n_both, n, 3))
    Jc = np.zeros((2, n))
    Jp = np.zeros((2, 3))
    for o in range(oc.shape[0]):
        c, p = oc[o], op[o]
        x0, x1, x2 = X[p, 0], X[p, 1], X[p, 2]
        h0, h1, h2 = _homogeneous(Ps, c, x0, x1, x2)
        u, v = h0 / h2, h1 / h2
        ru, rv = u - xy[o, 0], v - xy[o, 1]
        norm = np.sqrt(ru * ru + rv * rv)
        w = 1.0 if norm <= delta else delta / max(norm, 1e-300)
        sc, sp = cam_slot[c], pt_slot[p]
        if sc >= 0:
            for j in range(n):
                d0 = dP[sc, j, 0, 0] * x0 + dP[sc, j, 0, 1] * x1 + dP[sc, j, 0, 2] * x2 + dP[sc, j, 0, 3]
                d1 = dP[sc, j, 1, 0] * x0 + dP[sc, j, 1, 1] * x1 + dP[sc, j, 1, 2] * x2 + dP[sc, j, 1, 3]
                d2 = dP[sc, j, 2, 0] * x0 + dP[sc, j, 2, 1] * x1 + dP[sc, j, 2, 2] * x2 + dP[sc, j, 2, 3]
                Jc[0, j] = (d0 - u * d2) / h2
                Jc[1, j] = (d1 - v * d2) / h2
            for a in range(n):
                gc[sc, a] += w * (Jc[0, a] * ru + Jc[1, a] * rv)
                for b in range(n):
                    U[sc, a, b] += w * (Jc[0, a] * Jc[0, b] + Jc[1, a] * Jc[1, b])
        if sp >= 0:
            for k in range(3):
                Jp[0, k] = (Ps[c, 0, k] - u * Ps[c, 2, k]) / h2
                Jp[1, k] = (Ps[c, 1, k] - v * Ps[c, 2, k]) / h2
            for a in range(3):
                gp[sp, a] += w * (Jp[0, a] * ru + Jp[1, a] * rv)
                for b in range(3):
                    V[sp, a, b] += w * (Jp[0, a] * Jp[0, b] + Jp[1, a] * Jp[1, b])
            if sc >= 0:
                row = both_row[o]
                for a in range(n):
                    for b in range(3):
                        W[row, a, b] = w * (Jc[0, a] * Jp[0, b] + Jc[1, a] * Jp[1, b])
    return U, gc, V, gp, W


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
        h0, h1, h2 = _homogeneous(Ps, oc[o], X[op[o], 0], X[op[o], 1], X[op[o], 2])
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
    thread_rows = _thread_rows(pair_order, point_starts, both_camera, nC)

    lam = 1e-3
    cost = huber_cost_of_norms(observation_errors(Ps, X, oc, op, xy), delta)
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        dP = _projection_derivatives(params, model, free_ref_K) if nC else np.zeros((0, n, 3, 4))
        U, gc, V, gp, Wb = _normal_equations(Ps, X, oc, op, xy, cam_slot, pt_slot, dP, float(delta), both_row,
                                            nC, nP, len(both_idx_all))

        Wt = np.swapaxes(Wb, 1, 2).copy()  # rows of W^T: contiguous for the reduced system's kernel
        def trial(lam: float) -> tuple[tuple, float]:  # called at once by damped_step, in this iteration
            Vinv, Y, rhs = _eliminate_points(V, gp, gc, Wb, lam, both_point, both_camera)
            if nC:
                S2 = damped_camera_system(pair_order, point_starts, both_camera, Wt, Y, U, lam, thread_rows)
                dc = _solve_symmetric(S2, rhs.ravel()).reshape(nC, n)
            else:
                dc = np.zeros((0, n))
            dp = _back_substitute(Vinv, gp, Wb, dc, both_point, both_camera)
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
