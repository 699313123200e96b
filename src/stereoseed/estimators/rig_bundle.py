"""Bundle adjustment of a stereo rig's walk: one pose per station, the rig held.

Each station is the left camera's pose (R, t); its right camera is the rig's
(:class:`stereoseed.estimators.rig_resection.Rig`: ``X_right = R_rl X_left + t_rl``), so both
images of a station move together and every station keeps the calibrated relative pose exactly.
The intrinsics are the rig's and held. With ``refine_rig`` the relative pose is refined once,
shared by all stations: its rotation and the direction of its translation; the baseline's length
is held, since it carries the model's scale (a fixed first station alone leaves the scale free).

The gauge: the fixed stations (by default the first) and the fixed points; at least one of them
must be given.

The solver is :mod:`stereoseed.estimators.bundle`'s: Levenberg-Marquardt on the Huber loss of each
observation's 2D error (iteratively reweighted), the points eliminated by the Schur complement
with that module's kernels. Its "cameras" are the free stations (6 parameters: a rotation
increment on the left, the translation) and, when refined, the rig (a rotation increment and 2
coordinates across the baseline, padded to 6). A right camera's observation depends on both its
station and the rig: it enters the kernels once per block (both with the point's Jacobian), which
is the Schur complement of the whole observation, and the station-rig block of the normal
equations is added here.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.sparse import csr_matrix

from stereoseed.estimators._schur import (back_substitute, damped_camera_system, eliminate_points, solve_symmetric,
                                         thread_rows)
from stereoseed.estimators.bundle import damped_step, observation_errors, pairs_by_point
from stereoseed.estimators.config import BundleConfig
from stereoseed.estimators.rig_resection import Rig
from stereoseed.estimators.robust import huber_cost_of_norms, huber_weights
from stereoseed.geometry.models import rotation_from_vector, rotations_from_vectors
from stereoseed.validation import positive, whole

__all__ = ["RigBundleConfig", "RigBundleProblem", "RigBundleResult", "rig_bundle_adjust", "rig_observation_errors",
           "station_projections"]

_N = 6  # parameters per block (a station's pose; the rig's 5, padded)


@dataclass(frozen=True)
class RigBundleConfig:
    huber_px: float = BundleConfig.huber_px  # the BA's Huber threshold on each 2D error; inf: least squares
    # LM iterations: the BA's 20 serve a local window after one insertion; a walk of stations
    # started from resections needs a few more
    max_iterations: int = 50
    # stop once an iteration lowers the cost by less than this fraction: the BA's own criterion
    min_improvement: float = 1e-6

    def __post_init__(self) -> None:
        positive(self, "huber_px", "min_improvement")
        whole(self, "max_iterations")


@dataclass
class RigBundleProblem:
    """What a rig bundle adjustment sees.

    rig: the rig (intrinsics and relative pose); R (N, 3, 3), t (N, 3): each station's left camera
    (``cam_from_world``); points (M, 3); obs_station, obs_side (0 left, 1 right), obs_point (O,)
    int; obs_xy (O, 2) undistorted pixels; free_stations (N,) bool or None (every station but the
    first); free_points (M,) bool or None (all); refine_rig: refine the relative pose (module
    docstring).
    """

    rig: Rig
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    obs_station: np.ndarray
    obs_side: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    free_stations: np.ndarray | None = None
    free_points: np.ndarray | None = None
    refine_rig: bool = False


@dataclass(frozen=True, eq=False)
class RigBundleResult:
    """R (N, 3, 3), t (N, 3), points (M, 3) refined (fixed ones unchanged); rig: the rig the
    stations use (the input one unless refined); RMS (px) over all observations before and after."""

    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    rig: Rig = field(repr=False)
    rms_before: float
    rms_after: float
    iterations: int
    seconds: float

    def projections(self) -> np.ndarray:
        """(N, 2, 3, 4): each station's P_left, P_right."""
        return station_projections(self.rig, self.R, self.t)


def station_projections(rig: Rig, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2, 3, 4): P_left, P_right of stations (R (N, 3, 3), t (N, 3)) of ``rig``."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    t = np.asarray(t, np.float64).reshape(-1, 3)
    Rr = np.einsum("ij,njk->nik", rig.R_rl, R)
    tr = t @ rig.R_rl.T + rig.t_rl
    left = np.einsum("ij,njk->nik", rig.K_left, np.concatenate([R, t[:, :, None]], axis=2))
    right = np.einsum("ij,njk->nik", rig.K_right, np.concatenate([Rr, tr[:, :, None]], axis=2))
    return np.stack([left, right], axis=1)


def rig_observation_errors(rig: Rig, R: np.ndarray, t: np.ndarray, points: np.ndarray, obs_station: np.ndarray,
                           obs_side: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray) -> np.ndarray:
    """Reprojection distance (O,) px of each observation in its station's camera (NaN or inf for
    a point on a camera's principal plane)."""
    Ps = station_projections(rig, R, t).reshape(-1, 3, 4)
    cams = 2 * np.asarray(obs_station, np.int64) + np.asarray(obs_side, np.int64)
    return observation_errors(Ps, points, cams, obs_point, obs_xy)


def _across(d: np.ndarray) -> np.ndarray:
    """(2, 3): two orthonormal directions across the unit vector d."""
    e1 = np.cross(d, np.eye(3)[int(np.argmin(np.abs(d)))])
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(d, e1)])


def _jacobians(rig: Rig, R: np.ndarray, t: np.ndarray, X: np.ndarray, st: np.ndarray, side: np.ndarray,
               pt: np.ndarray, xy: np.ndarray) -> tuple:
    """Residuals r (O, 2) and their Jacobians with respect to the station's increments (O, 2, 6),
    the rig's (O, 2, 6: rotation, 2 across the baseline, a zero pad; zero for the left camera)
    and the point (O, 2, 3), at the current estimate (:func:`_jacobian_kernel`)."""
    O = len(st)
    out = np.zeros((O, 2)), np.zeros((O, 2, _N)), np.zeros((O, 2, _N)), np.zeros((O, 2, 3))
    across = rig.baseline * _across(rig.t_rl / rig.baseline) if rig.baseline > 0 else np.zeros((2, 3))
    _jacobian_kernel(np.ascontiguousarray(R), np.ascontiguousarray(t), np.ascontiguousarray(X), rig.Ks, rig.R_rl,
                     rig.t_rl, np.ascontiguousarray(across), st, side, pt, np.ascontiguousarray(xy), *out)
    return out


@njit(cache=True, nogil=True)
def _jacobian_kernel(R, t, X, Ks, R_rl, t_rl, across, st, side, pt, xy, r, J_station, J_rig, J_point):
    """One pass over the observations (the BA's hot loop; small products written out): the
    station's point Y = R X + t, the right camera's Z = R_rl Y + t_rl (the left's Z = Y), the
    pixel through the side's K; d(pixel)/dZ = D, dZ/dY = R_rl (right) or I, dY/dw = -[R X]x for
    the rotation increment w (R <- exp([w]x) R), dY/dt = I, dY/dX = R; for the rig,
    dZ/dw_rig = -[R_rl Y]x and dZ/da = ``across`` (b times the two directions across it)."""
    D = np.empty((2, 3))
    DY = np.empty((2, 3))
    RX = np.empty(3)
    Y = np.empty(3)
    Z = np.empty(3)
    for o in range(st.shape[0]):
        s, p, c = st[o], pt[o], side[o]
        for i in range(3):
            RX[i] = R[s, i, 0] * X[p, 0] + R[s, i, 1] * X[p, 1] + R[s, i, 2] * X[p, 2]
            Y[i] = RX[i] + t[s, i]
        for i in range(3):
            Z[i] = R_rl[i, 0] * Y[0] + R_rl[i, 1] * Y[1] + R_rl[i, 2] * Y[2] + t_rl[i] if c == 1 else Y[i]
        iz = 1.0 / Z[2]
        nx, ny = Z[0] * iz, Z[1] * iz
        for a in range(2):  # the residual, and D = K[:2, :2] @ d(nx, ny)/dZ
            r[o, a] = Ks[c, a, 0] * nx + Ks[c, a, 1] * ny + Ks[c, a, 2] - xy[o, a]
            D[a, 0] = Ks[c, a, 0] * iz
            D[a, 1] = Ks[c, a, 1] * iz
            D[a, 2] = -(Ks[c, a, 0] * nx + Ks[c, a, 1] * ny) * iz
        for a in range(2):
            for k in range(3):
                DY[a, k] = D[a, 0] * R_rl[0, k] + D[a, 1] * R_rl[1, k] + D[a, 2] * R_rl[2, k] if c == 1 else D[a, k]
        if c == 1:
            RY0, RY1, RY2 = Z[0] - t_rl[0], Z[1] - t_rl[1], Z[2] - t_rl[2]
            for a in range(2):  # D @ -[R_rl Y]x, then D @ across^T
                J_rig[o, a, 0] = D[a, 2] * RY1 - D[a, 1] * RY2
                J_rig[o, a, 1] = D[a, 0] * RY2 - D[a, 2] * RY0
                J_rig[o, a, 2] = D[a, 1] * RY0 - D[a, 0] * RY1
                for k in range(2):
                    J_rig[o, a, 3 + k] = D[a, 0] * across[k, 0] + D[a, 1] * across[k, 1] + D[a, 2] * across[k, 2]
        for a in range(2):
            J_station[o, a, 0] = DY[a, 2] * RX[1] - DY[a, 1] * RX[2]  # DY @ -[RX]x
            J_station[o, a, 1] = DY[a, 0] * RX[2] - DY[a, 2] * RX[0]
            J_station[o, a, 2] = DY[a, 1] * RX[0] - DY[a, 0] * RX[1]
            for k in range(3):
                J_station[o, a, 3 + k] = DY[a, k]
                J_point[o, a, k] = DY[a, 0] * R[s, 0, k] + DY[a, 1] * R[s, 1, k] + DY[a, 2] * R[s, 2, k]


def _check(problem: RigBundleProblem) -> tuple[np.ndarray, np.ndarray]:
    n_st = len(np.asarray(problem.R).reshape(-1, 3, 3))
    n_pt = len(np.asarray(problem.points).reshape(-1, 3))
    free_st = np.arange(n_st) > 0 if problem.free_stations is None else np.asarray(problem.free_stations, bool)
    free_pt = np.ones(n_pt, bool) if problem.free_points is None else np.asarray(problem.free_points, bool)
    if free_st.shape != (n_st,) or free_pt.shape != (n_pt,) or np.asarray(problem.t).reshape(-1, 3).shape[0] != n_st:
        raise ValueError(f"RigBundleProblem: {n_st} stations and {n_pt} points need free_stations ({n_st},), "
                         f"t ({n_st}, 3) and free_points ({n_pt},)")
    O = len(problem.obs_station)
    if not (len(problem.obs_side) == len(problem.obs_point) == O and np.shape(problem.obs_xy) == (O, 2)):
        raise ValueError("RigBundleProblem: obs_station, obs_side, obs_point (O,) and obs_xy (O, 2) must agree")
    if free_st.all() and free_pt.all():
        raise ValueError("RigBundleProblem: every station and every point is free: the gauge is not fixed "
                         "(hold a station or some points)")
    return free_st, free_pt


def _sum_blocks(slots: np.ndarray, blocks: np.ndarray, n: int) -> np.ndarray:
    """The sum of blocks (K, ...) per slot (K,) in [0, n): (n, ...), as one sparse product
    (a fraction of ``np.add.at``'s time)."""
    gather = csr_matrix((np.ones(len(slots)), (slots, np.arange(len(slots)))), shape=(n, len(slots)))
    return np.asarray(gather @ blocks.reshape(len(slots), int(np.prod(blocks.shape[1:])))).reshape((n,) + blocks.shape[1:])


def _gram(w: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """w_k A_k^T B_k of each row: w (K,), A (K, 2, a), B (K, 2, b) -> (K, a, b)."""
    return np.matmul(np.swapaxes(A * w[:, None, None], 1, 2), B)


def _step(rig: Rig, R, t, X, dc: np.ndarray, dp: np.ndarray, free_idx: np.ndarray, pt_idx: np.ndarray,
          rig_slot: int) -> tuple:
    """The estimate moved by the cameras' step dc (blocks, 6) and the points' dp (free points, 3)."""
    R, t, X = R.copy(), t.copy(), X.copy()
    n_st = len(free_idx)
    if n_st:
        R[free_idx] = rotations_from_vectors(dc[:n_st, :3]) @ R[free_idx]
        t[free_idx] += dc[:n_st, 3:]
    X[pt_idx] += dp
    if rig_slot >= 0:
        d = rig.t_rl / rig.baseline
        v = d + dc[rig_slot, 3:5] @ _across(d)
        rig = Rig(rig.K_left, rig.K_right, rotation_from_vector(dc[rig_slot, :3]) @ rig.R_rl,
                  rig.baseline * v / np.linalg.norm(v))
    return rig, R, t, X


def rig_bundle_adjust(problem: RigBundleProblem, config: RigBundleConfig = RigBundleConfig()) -> RigBundleResult:
    """Minimise the robust reprojection error of the rig's observations over the free stations,
    the free points and, with ``refine_rig``, the shared relative pose (module docstring)."""
    t0 = time.perf_counter()
    free_st, free_pt = _check(problem)
    rig = problem.rig
    R = np.array(problem.R, np.float64).reshape(-1, 3, 3)
    t = np.array(problem.t, np.float64).reshape(-1, 3)
    X = np.array(problem.points, np.float64).reshape(-1, 3)
    st, side, pt = (np.asarray(a, np.int64) for a in (problem.obs_station, problem.obs_side, problem.obs_point))
    xy = np.asarray(problem.obs_xy, np.float64)
    delta = config.huber_px

    every = (st, side, pt, xy)

    def rms(rig_: Rig, R_: np.ndarray, t_: np.ndarray, X_: np.ndarray) -> float:
        return float(np.sqrt(np.mean(rig_observation_errors(rig_, R_, t_, X_, *every) ** 2))) if len(every[0]) else 0.0

    rms_before = rms(rig, R, t, X)
    free_idx, pt_idx = np.flatnonzero(free_st), np.flatnonzero(free_pt)
    refine_rig = problem.refine_rig and bool(np.any(side == 1))
    if refine_rig and not rig.baseline > 0:
        raise ValueError("RigBundleProblem: a rig without a baseline has no direction to refine")
    st_slot = np.full(len(R), -1, np.int64)
    st_slot[free_idx] = np.arange(len(free_idx))
    rig_slot = len(free_idx) if refine_rig else -1
    n_cams = len(free_idx) + (1 if refine_rig else 0)
    p_slot = np.full(len(X), -1, np.int64)
    p_slot[pt_idx] = np.arange(len(pt_idx))
    # only observations touching something free matter: the others add a constant
    relevant = (st_slot[st] >= 0) | (p_slot[pt] >= 0) | (refine_rig & (side == 1))
    st, side, pt, xy = st[relevant], side[relevant], pt[relevant], xy[relevant]
    if not len(st) or (n_cams == 0 and not len(pt_idx)):
        return RigBundleResult(R, t, X, rig, rms_before, rms_before, 0, time.perf_counter() - t0)

    # Each observation enters the Schur kernels once per free block it depends on ("virtual"
    # observations): its station, and the rig for a right camera's when the rig is refined.
    obs_cam = st_slot[st]
    obs_pt = p_slot[pt]
    by_station = np.flatnonzero(obs_cam >= 0)
    by_rig = np.flatnonzero(side == 1) if refine_rig else np.zeros(0, np.int64)
    virt_obs = np.concatenate([by_station, by_rig])
    virt_cam = np.concatenate([obs_cam[by_station], np.full(len(by_rig), rig_slot, np.int64)])
    both = obs_pt[virt_obs] >= 0  # the virtual observations of free points: the rows of W
    w_obs, w_cam, w_pt = virt_obs[both], virt_cam[both], obs_pt[virt_obs[both]]
    pair_order, starts = pairs_by_point(w_pt, w_cam)
    rows = thread_rows(pair_order, starts, w_cam, n_cams) if n_cams else None
    cross = np.flatnonzero((obs_cam >= 0) & (side == 1)) if refine_rig else np.zeros(0, np.int64)
    point_obs = np.flatnonzero(obs_pt >= 0)

    def cost_of(rig_: Rig, R_: np.ndarray, t_: np.ndarray, X_: np.ndarray) -> float:
        with np.errstate(all="ignore"):  # a trial step may put a point on a principal plane: refused
            return huber_cost_of_norms(rig_observation_errors(rig_, R_, t_, X_, st, side, pt, xy), delta)

    lam = 1e-3
    cost = cost_of(rig, R, t, X)
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        r, J_st, J_rig, J_pt = _jacobians(rig, R, t, X, st, side, pt, xy)
        norm = np.linalg.norm(r, axis=1)
        w = huber_weights(norm, delta)
        J_virt = np.concatenate([J_st[by_station], J_rig[by_rig]])  # (virtual, 2, 6)
        w_virt = w[virt_obs]
        U = _sum_blocks(virt_cam, _gram(w_virt, J_virt, J_virt), n_cams)
        gc = _sum_blocks(virt_cam, _gram(w_virt, J_virt, r[virt_obs, :, None])[:, :, 0], n_cams)
        Jp, wp = J_pt[point_obs], w[point_obs]
        V = _sum_blocks(obs_pt[point_obs], _gram(wp, Jp, Jp), len(pt_idx))
        gp = _sum_blocks(obs_pt[point_obs], _gram(wp, Jp, r[point_obs, :, None])[:, :, 0], len(pt_idx))
        W = np.ascontiguousarray(_gram(w[w_obs], J_virt[both], J_pt[w_obs]))  # (rows, 6, 3)
        U_cross = _sum_blocks(obs_cam[cross], _gram(w[cross], J_st[cross], J_rig[cross]), n_cams)
        Wt = np.swapaxes(W, 1, 2).copy()
        def trial(lam: float) -> tuple[tuple | None, float]:  # called at once by damped_step, in this iteration
            Vinv, Y, rhs = eliminate_points(V, gp, gc, W, lam, w_pt, w_cam)
            if n_cams:
                S = damped_camera_system(pair_order, starts, w_cam, Wt, Y, U, lam, rows)
                if refine_rig:  # the station-rig blocks no single observation block carries
                    g = slice(rig_slot * _N, (rig_slot + 1) * _N)
                    for c in range(len(free_idx)):
                        S[c * _N:(c + 1) * _N, g] += U_cross[c]
                        S[g, c * _N:(c + 1) * _N] += U_cross[c].T
                dc = solve_symmetric(S, rhs.ravel()).reshape(n_cams, _N)
            else:
                dc = np.zeros((0, _N))
            dp = back_substitute(Vinv, gp, W, dc, w_pt, w_cam)
            if not np.all(np.isfinite(dc)):
                return None, np.inf
            moved = _step(rig, R, t, X, dc, dp, free_idx, pt_idx, rig_slot)
            return moved, cost_of(*moved)

        moved, cost, lam, improvement = damped_step(trial, cost, lam)
        if moved is not None:
            rig, R, t, X = moved
        if improvement < config.min_improvement:
            break
    return RigBundleResult(R, t, X, rig, rms_before, rms(rig, R, t, X), iterations, time.perf_counter() - t0)
