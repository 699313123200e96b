"""The Schur complement machinery of the bundle adjustments (:mod:`stereoseed.estimators.bundle`,
:mod:`stereoseed.estimators.rig_bundle`) and of the cameras' covariance
(:mod:`stereoseed.estimators.covariance`): the normal equations of the robust reprojection
error, the points eliminated (Triggs et al. 2000, §6.1), the reduced camera system formed in
threads, solved, and the points' steps recovered.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from stereoseed.threads import current_chunks, map_chunks

__all__ = ["solve_symmetric", "eliminate_points", "back_substitute", "thread_rows", "damped_camera_system",
           "reduced_camera_matrix", "homogeneous", "normal_equations", "camera_scores", "PAIRS_PER_THREAD"]

# Threads forming the reduced camera system: the cores this process may use (threads.py), at
# most 4 (the loop is memory-bound beyond that); below PAIRS_PER_THREAD observation pairs a
# thread costs more than it saves (a pair is ~10 ns, a thread's start ~50 us).
_MAX_THREADS = 4
PAIRS_PER_THREAD = 20_000


def solve_symmetric(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
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
def eliminate_points(V, gp, gc, W, lam, point, camera):
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
def back_substitute(Vinv, gp, W, dc, point, camera):
    """The points' step dp (P, 3) = V^-1 (-gp - sum W^T dc) once the cameras' step dc (C, n) is
    known (arguments as :func:`eliminate_points`)."""
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


def thread_rows(order: np.ndarray, starts: np.ndarray, cams: np.ndarray, n_cams: int) -> np.ndarray:
    """How :func:`reduced_camera_matrix` shares its block rows among threads: (T + 1,) camera
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
    (C n, C n). Arguments as :func:`reduced_camera_matrix`."""
    n_cams, n = U.shape[0], U.shape[1]
    eye = np.eye(n)
    S = reduced_camera_matrix(order, starts, cams, Wt, Y, n_cams, rows)
    Ud = U + lam * (U * eye) + 1e-12 * eye
    for i in range(n_cams):
        S[i * n:(i + 1) * n, i * n:(i + 1) * n] += Ud[i]
    return S


def reduced_camera_matrix(order: np.ndarray, starts: np.ndarray, cams: np.ndarray, Wt: np.ndarray, Y: np.ndarray,
                           n_cams: int, rows: np.ndarray) -> np.ndarray:
    """-W V^-1 W^T of the reduced camera system, camera-major (n_cams n, n_cams n). Forming it
    costs the sum over points of (track length)^2 blocks: its block rows are shared among the
    threads of ``rows`` (:func:`thread_rows`; the kernel releases the GIL)."""
    n = Wt.shape[2]
    S = np.zeros((n_cams * n, n_cams * n))
    map_chunks(lambda first, end: _add_point_pairs(S, order, starts, cams, Wt, Y, first, end), rows)
    _mirror_upper(S, n)
    return S


@njit(cache=True, nogil=True, inline="always")
def homogeneous(Ps, c, x0, x1, x2):
    """Ps[c] @ (x0, x1, x2, 1): the homogeneous pixel of a point in camera c of Ps (C, 3, 4)."""
    return (Ps[c, 0, 0] * x0 + Ps[c, 0, 1] * x1 + Ps[c, 0, 2] * x2 + Ps[c, 0, 3],
            Ps[c, 1, 0] * x0 + Ps[c, 1, 1] * x1 + Ps[c, 1, 2] * x2 + Ps[c, 1, 3],
            Ps[c, 2, 0] * x0 + Ps[c, 2, 1] * x1 + Ps[c, 2, 2] * x2 + Ps[c, 2, 3])


@njit(cache=True, nogil=True, inline="always")
def camera_derivative(dP, sc, j, x0, x1, x2, u, v, h2):
    """(du, dv): how the pixel (u, v) of the point (x0, x1, x2), whose homogeneous pixel has
    depth h2, moves with parameter j of the free camera in slot sc (dP (n_cams, n, 3, 4): dP/dparams)."""
    d0 = dP[sc, j, 0, 0] * x0 + dP[sc, j, 0, 1] * x1 + dP[sc, j, 0, 2] * x2 + dP[sc, j, 0, 3]
    d1 = dP[sc, j, 1, 0] * x0 + dP[sc, j, 1, 1] * x1 + dP[sc, j, 1, 2] * x2 + dP[sc, j, 1, 3]
    d2 = dP[sc, j, 2, 0] * x0 + dP[sc, j, 2, 1] * x1 + dP[sc, j, 2, 2] * x2 + dP[sc, j, 2, 3]
    return (d0 - u * d2) / h2, (d1 - v * d2) / h2


@njit(cache=True, nogil=True)
def normal_equations(Ps, X, oc, op, xy, weight, cam_slot, pt_slot, dP, delta, both_row, n_cams, n_points, n_both):
    """The Gauss-Newton blocks of the robust (Huber, IRLS) reprojection error, one pass over the
    observations with nothing stored per observation but W: U (n_cams, n, n) and gc (n_cams, n)
    of the free cameras, V (n_points, 3, 3) and gp (n_points, 3) of the free points, and
    W (n_both, n, 3) = w Jc^T Jp of each observation of a free point by a free camera (its row
    ``both_row[o]``). Ps (C, 3, 4), X (M, 3); oc, op (O,) observation -> camera, point;
    xy (O, 2); weight (O,) each observation's weight (1: a whole independent observation; the
    covariance counts correlated ones as a share of one); cam_slot (C,), pt_slot (M,) the free
    index or -1; dP (n_cams, n, 3, 4) dP/dparams of each free camera."""
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
        h0, h1, h2 = homogeneous(Ps, c, x0, x1, x2)
        u, v = h0 / h2, h1 / h2
        ru, rv = u - xy[o, 0], v - xy[o, 1]
        norm = np.sqrt(ru * ru + rv * rv)
        w = (1.0 if norm <= delta else delta / max(norm, 1e-300)) * weight[o]
        sc, sp = cam_slot[c], pt_slot[p]
        if sc >= 0:
            for j in range(n):
                Jc[0, j], Jc[1, j] = camera_derivative(dP, sc, j, x0, x1, x2, u, v, h2)
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


@njit(cache=True, nogil=True)
def camera_scores(Ps, X, oc, op, xy, weight, cam_slot, dP):
    """Each observation's share of the free cameras' gradient, w Jc^T r (O, n): what
    :func:`normal_equations` sums into gc, kept per observation (zero for a fixed camera's) so
    that a covariance can sum it over clusters of observations instead. Arguments as
    :func:`normal_equations`' (plain least squares: no Huber weight)."""
    n = dP.shape[1]
    out = np.zeros((oc.shape[0], n))
    for o in range(oc.shape[0]):
        c, p = oc[o], op[o]
        sc = cam_slot[c]
        if sc < 0:
            continue
        x0, x1, x2 = X[p, 0], X[p, 1], X[p, 2]
        h0, h1, h2 = homogeneous(Ps, c, x0, x1, x2)
        u, v = h0 / h2, h1 / h2
        ru, rv = u - xy[o, 0], v - xy[o, 1]
        for j in range(n):
            du, dv = camera_derivative(dP, sc, j, x0, x1, x2, u, v, h2)
            out[o, j] = weight[o] * (du * ru + dv * rv)
    return out
