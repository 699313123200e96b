"""The uncertainty of each camera of a bundle adjustment: the covariance of its parameters.

What COLMAP (``estimators/covariance.h``) and Ceres (``Covariance``) compute for a parameter
block: at the solution, the Gauss-Newton normal equations J^T J of the reprojection error over
the free cameras and points, [[U, W], [W^T, V]], the points eliminated as in the bundle
adjustment's LM (:mod:`stereoseed.estimators.bundle`, whose kernels build them here too):
S = U - W V^-1 W^T, the information of the cameras with every point's position unknown. The
covariance of the cameras is sigma^2 S^-1 (Triggs et al. 2000, "Bundle adjustment - a modern
synthesis", §2.2 and §6.1; Hartley & Zisserman, §5.2.3), sigma the pixel noise: given, or the
residual variance RSS / (2 n_obs - n_params) at the solution (n_params: the rank of J).

The gauge: the cameras that are not free (the calibrated pair) are constants and carry the
metric frame, so S is invertible when the free cameras are determined by them. Where it is
singular or ill-conditioned (a camera seeing too few points, a single fixed camera leaving the
scale free), the cameras taking part in its weak directions are reported undetermined - infinite
sigmas and a reason - never a number; the others keep theirs (the weak directions do not touch
their parameters, so they are the marginal covariance of those parameters).

The parameters of a camera are the model's (:class:`stereoseed.geometry.models.CameraModel`):
its intrinsics, then a rotation increment w (rad) about the camera's own axes (R <- exp([w]x) R,
the tangent space Ceres' manifolds use; :func:`stereoseed.geometry.models.projection_derivatives`),
then t. The residuals' own spread (``point_clusters``): the cluster-robust ("sandwich") covariance
S^-1 M S^-1, M the sum over clusters of points of r r^T, r a cluster's share of the reduced
gradient g_cam - W V^-1 g_pt (White 1980; the linearised jackknife over the clusters). It needs
no noise model: where the matches of one region share their errors (propagated matches, a
pattern matched one period over), it grows past sigma^2 S^-1, which counts each observation as
independent. The covariance reported is the larger of the two by its worst axis' position sigma
(what the flags judge).
Plain least squares, without the BA's Huber weights: for Gaussian pixel noise the Huber
estimate (1 px, sigma 0.5 px) spreads within ~3 % of what this predicts (Monte Carlo, see the
tests); an outlier would count at full weight, so drop outliers first (the mapper does).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from stereoseed.estimators._schur import (camera_scores, eliminate_points, normal_equations, reduced_camera_matrix,
                                          thread_rows)
from stereoseed.estimators.bundle import BundleProblem, observation_errors, pairs_by_point
from stereoseed.geometry import models as camera_models
from stereoseed.geometry.models import CameraModel

__all__ = ["CameraUncertainty", "camera_uncertainty", "one_per_cell", "point_regions", "parameter_names"]

log = logging.getLogger(__name__)

# A direction of the Jacobi-scaled reduced camera system (unit diagonal, so its eigenvalues are
# at most its size) weaker than RCOND times the strongest is treated as undetermined: an exact
# singularity comes out near 1e-16 (a camera seeing two points, a free scale: the tests), and a
# real direction at 1e-10 would already give sigmas 1e5 times those of a camera whose
# parameters were uncorrelated - nothing a report should print as a number.
RCOND = 1e-10
# A camera is undetermined when its parameters carry more than this share of the (unit-norm)
# weak directions: an exact null vector of another camera has roundoff-sized components here.
WEAK_SHARE = 1e-6
# A point whose 3x3 block V has reciprocal condition below this (rays within ~0.01 degrees:
# from nearly the same centre) is left out: its elimination U - W V^-1 W^T cancels in the low
# digits, and on two nearly coincident cameras (a photo taken twice from one spot:
# templeSparseRing's 0001 and 0011, 0.02 mm apart as estimated) the points only they see made
# the reduced system singular along their joint rotation (at 1e-12; each alone: 0.2-0.5 mm).
# sqrt(machine epsilon): half the digits kept. Its depth is roundoff; what it says of the
# cameras' rotations is given up, which only makes their sigmas larger (conservative).
POINT_RCOND = 1e-8

_INTRINSIC_NAMES = {CameraModel.FREE: ("fx", "fy", "skew", "cx", "cy"), CameraModel.ZERO_SKEW: ("f", "cx", "cy"),
                    CameraModel.FOCAL: ("f",), CameraModel.FIXED: ()}


def parameter_names(model: str) -> tuple[str, ...]:
    """The names of a camera's parameters under ``model``, in the covariance's order: the
    intrinsics (px), wx wy wz (rad, about the camera's axes), tx ty tz (the model's unit)."""
    return _INTRINSIC_NAMES[CameraModel(model)] + ("wx", "wy", "wz", "tx", "ty", "tz")


def _json_floats(a: np.ndarray) -> list:
    """Nested lists of floats, non-finite entries as None (JSON has no inf or NaN)."""
    a = np.asarray(a, np.float64)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_json_floats(x) for x in a]


@dataclass(frozen=True, eq=False)
class CameraUncertainty:
    """The 1-sigma uncertainty of one free camera.

    position_sigma (3,): of the camera centre C = -R^T t along the camera's own axes (x right,
    y down, z forward), in the model's (world) unit: that of the larger (by its worst axis) of
    model_position_sigma (from the pixel noise, sigma^2 S^-1) and measured_position_sigma (the
    residuals' own spread over clusters of points), each (3,) or None when not computed.
    rotation_sigma_deg (3,): of the rotation about those axes, degrees (the larger of the two). focal_sigma_px: of fx in px (f for the 'zero-skew' and 'focal'
    models), None for the 'fixed' model. covariance (n, n): the camera's block, in the order of
    ``parameters`` (:func:`parameter_names`: intrinsics px, w rad, t unit). position_covariance
    (3, 3): of the centre, in the camera's axes. sigma_px: the pixel noise used. An undetermined
    camera has infinite sigmas, a NaN covariance and ``reason`` saying why.
    """

    position_sigma: np.ndarray
    rotation_sigma_deg: np.ndarray
    focal_sigma_px: float | None
    covariance: np.ndarray
    position_covariance: np.ndarray
    parameters: tuple[str, ...]
    sigma_px: float
    reason: str | None = None
    model_position_sigma: np.ndarray | None = None
    measured_position_sigma: np.ndarray | None = None

    @property
    def determined(self) -> bool:
        return self.reason is None

    def summary(self) -> dict:
        """What a report keeps of it (:meth:`to_dict` without the covariance matrices)."""
        d = self.to_dict()
        return {k: d[k] for k in ("position_sigma", "model_position_sigma", "measured_position_sigma",
                                  "rotation_sigma_deg", "focal_sigma_px", "sigma_px", "reason")}

    def to_dict(self) -> dict:
        """JSON-ready: finite floats, non-finite ones as None, plus ``reason`` (None when
        determined)."""
        return {"position_sigma": _json_floats(self.position_sigma),
                "model_position_sigma": None if self.model_position_sigma is None else
                _json_floats(self.model_position_sigma),
                "measured_position_sigma": None if self.measured_position_sigma is None else
                _json_floats(self.measured_position_sigma),
                "rotation_sigma_deg": _json_floats(self.rotation_sigma_deg),
                "focal_sigma_px": None if self.focal_sigma_px is None else _json_floats(self.focal_sigma_px),
                "parameters": list(self.parameters),
                "covariance": _json_floats(self.covariance),
                "position_covariance": _json_floats(self.position_covariance),
                "sigma_px": _json_floats(self.sigma_px),
                "reason": self.reason}


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, np.float64)
    a.flags.writeable = False
    return a


def _centre_jacobian(t: np.ndarray, n: int) -> np.ndarray:
    """d(R dC)/dparams (3, n): how the centre C = -R^T t moves, in the camera's axes, with the
    parameters (intrinsics, w, t). With R' = (I + [w]x) R and t' = t + dt,
    C' = -R^T (I - [w]x)(t + dt), so R dC = [w]x t - dt = -[t]x w - dt; K does not move it."""
    tx, ty, tz = t
    J = np.zeros((3, n))
    J[:, n - 6:n - 3] = -np.array([[0.0, -tz, ty], [tz, 0.0, -tx], [-ty, tx, 0.0]])
    J[:, n - 3:] = -np.eye(3)
    return J


def _undetermined(names: tuple[str, ...], has_focal: bool, sigma: float, reason: str) -> CameraUncertainty:
    n = len(names)
    return CameraUncertainty(_frozen(np.full(3, np.inf)), _frozen(np.full(3, np.inf)), np.inf if has_focal else None,
                             _frozen(np.full((n, n), np.nan)), _frozen(np.full((3, 3), np.nan)), names, sigma, reason)


def _usable_points(op: np.ndarray, oc: np.ndarray, free_pts: np.ndarray, n_cams: int) -> np.ndarray:
    """(M,) bool: the points whose observations enter the normal equations. A free point seen
    from fewer than two distinct cameras has a singular V (its depth is free): it can absorb
    any move of its one camera, so it carries no information about the cameras and is
    skipped. Fixed points are constants: every observation of one pins its camera."""
    pairs = np.unique(op * n_cams + oc)  # distinct (point, camera)
    views = np.bincount(pairs // n_cams, minlength=len(free_pts))
    return ~free_pts | (views >= 2)


def _inverse_camera_blocks(S: np.ndarray, n: int, meat: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray | None]:
    """The (n, n) diagonal blocks of S^-1 for S (N n, N n) symmetric positive semi-definite:
    (blocks (N, n, n), determined (N,) bool, worst (N,) the weakest scaled eigenvalue a camera
    takes part in, relative to the strongest, NaN for a determined camera; the number of weak
    directions, S's rank deficiency; with ``meat`` (N n, N n), the diagonal blocks of the sandwich
    S^-1 meat S^-1 (N, n, n), else None).

    S is first scaled to unit diagonal (Jacobi: focal lengths in px, rotations in rad and
    translations in metres differ by 1e6 in scale, which would swamp any threshold). Fast path:
    Cholesky, accepted when no parameter's variance inflation factor (the diagonal of the scaled
    inverse, 1 / (1 - R^2) of the parameter against all the others) exceeds 1 / RCOND. Else the
    eigen-decomposition: the directions below RCOND are dropped (the pseudo-inverse), and the
    cameras with a share of them are undetermined. A parameter nothing observes (zero diagonal)
    has a zero row (S is PSD): a zero eigenvalue, so its camera is undetermined."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve

    N = len(S) // n
    d = np.diag(S).copy()
    scale = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    Sh = S * scale[:, None] * scale[None, :]
    blocks = np.full((N, n, n), np.nan)
    if not np.isfinite(Sh).all():
        return blocks, np.zeros(N, bool), np.full(N, np.nan), len(S), None if meat is None else blocks.copy()
    inverse = None
    try:
        inverse = cho_solve(cho_factor(Sh, lower=True, check_finite=False), np.eye(len(S)), check_finite=False)
        if not (np.all(d > 0) and np.isfinite(inverse).all() and np.diag(inverse).max() < 1.0 / RCOND):
            inverse = None
    except (LinAlgError, ValueError):
        pass
    if inverse is not None:
        determined = np.ones(N, bool)
        worst = np.full(N, np.nan)
        n_weak = 0
    else:
        lam, Q = np.linalg.eigh(Sh)
        weak = lam < RCOND * max(lam[-1], 0.0)
        share = (Q[:, weak] ** 2).reshape(N, n, -1).sum(axis=1)  # (N, weak) per camera
        determined = share.sum(axis=1) <= WEAK_SHARE
        rel = lam[weak] / max(lam[-1], 1e-300)
        # for the reason: the weak direction each camera takes the largest part in
        worst = np.where(determined, np.nan, rel[np.argmax(share, axis=1)] if weak.any() else np.nan)
        strong = Q[:, ~weak]
        n_weak = int(weak.sum())
        inverse = (strong / lam[~weak]) @ strong.T
    for i in np.flatnonzero(determined):
        sl = slice(i * n, (i + 1) * n)
        blocks[i] = inverse[sl, sl] * scale[sl, None] * scale[None, sl]
    if meat is None:
        return blocks, determined, worst, n_weak, None
    rows_of = inverse * scale[:, None] * scale[None, :]
    sandwich = np.full((N, n, n), np.nan)
    for i in np.flatnonzero(determined):
        rows = rows_of[i * n:(i + 1) * n]
        sandwich[i] = rows @ meat @ rows.T
    return blocks, determined, worst, n_weak, sandwich


def _grouped_camera_blocks(S: np.ndarray, n: int, free_cams: np.ndarray, group: np.ndarray, A: np.ndarray,
                           meat: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray | None, int]:
    """:func:`_inverse_camera_blocks` for cameras whose parameters are A_c @ (their group's), S
    the free cameras' reduced system (nC n, nC n): the groups' system T^T S T inverted, mapped
    back to each camera (a camera is determined when its group is): :func:`_inverse_camera_blocks`'
    five (the sandwich's with ``meat``, the free cameras' as S), then the number of groups."""
    nC = len(free_cams)
    ids, slot = np.unique(np.asarray(group)[free_cams], return_inverse=True)
    T = np.zeros((nC * n, len(ids) * n))
    for i, c in enumerate(free_cams):
        T[i * n:(i + 1) * n, slot[i] * n:(slot[i] + 1) * n] = A[c]
    g_blocks, g_determined, g_worst, n_weak, g_sandwich = _inverse_camera_blocks(
        T.T @ S @ T, n, None if meat is None else T.T @ meat @ T)
    blocks = np.einsum("cij,cjk,clk->cil", A[free_cams], g_blocks[slot], A[free_cams])
    sandwich = None if g_sandwich is None else np.einsum("cij,cjk,clk->cil", A[free_cams], g_sandwich[slot],
                                                         A[free_cams])
    return blocks, g_determined[slot], g_worst[slot], n_weak, sandwich, len(ids)


def one_per_cell(obs_camera: np.ndarray, obs_xy: np.ndarray, cell_px: float) -> np.ndarray:
    """(O,) float64: each observation's share of one independent observation, 1 / the number of
    observations of its camera in its square cell of ``cell_px`` pixels (obs_camera (O,) int,
    obs_xy (O, 2) px). Matches whose correlation windows overlap share pixels, so their errors
    are not independent: a region matched pixel by pixel (propagated matches) is one piece of
    evidence per window, not one per pixel. Every observation keeps its share, so every point
    stays seen from all its cameras."""
    if len(obs_camera) == 0:
        return np.zeros(0)
    cells = np.floor(np.asarray(obs_xy, np.float64) / cell_px)
    cells[~np.isfinite(cells)] = -1.0
    keys = np.stack([np.asarray(obs_camera, np.int64), cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)])
    _, cell, counts = np.unique(keys, axis=1, return_inverse=True, return_counts=True)
    return 1.0 / counts[cell.ravel()]


def point_regions(obs_camera: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray, n_points: int,
                  cell_px: float) -> np.ndarray:
    """(n_points,) int64: a region id per point, the square image cell of ``cell_px`` pixels its
    first observation (in the lowest-numbered camera) falls in, in that camera (obs_camera,
    obs_point (O,) int, obs_xy (O, 2) px): neighbouring points of one view share a region. A
    point nothing observes gets a region of its own."""
    out = np.arange(n_points, dtype=np.int64) + n_points  # (beyond every cell's id)
    if len(obs_camera) == 0:
        return out
    oc, op = np.asarray(obs_camera, np.int64), np.asarray(obs_point, np.int64)
    order = np.lexsort((oc, op))
    first = order[np.r_[True, op[order][1:] != op[order][:-1]]]
    cells = np.floor(np.asarray(obs_xy, np.float64)[first] / cell_px)
    cells[~np.isfinite(cells)] = -1.0
    keys = np.stack([oc[first], cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)])
    _, region = np.unique(keys, axis=1, return_inverse=True)
    out[op[first]] = region.ravel()
    return out


def _cluster_meat(Ps, X, oc, op, xy, weight, cam_slot, dP, gp, Y, both_idx, both_point, both_camera,
                  point_clusters: np.ndarray, nC: int) -> np.ndarray:
    """M = sum over clusters of (r_c - mean)(r_c - mean)^T (nC n, nC n), r_c the cluster's share
    of the cameras' reduced gradient g_cam - W V^-1 g_pt; a cluster holds whole points (``point_clusters`` (M,)
    its id per point), so the points' gradient it eliminates is its own. Times G / (G - 1) for G
    clusters (the small-sample factor of the cluster-robust "CR1" estimator; the caller applies
    its other factor, the residuals' degrees of freedom)."""
    from scipy import sparse

    n = dP.shape[1]
    scores = camera_scores(Ps, X, oc, op, xy, weight, cam_slot, dP)
    on_free = cam_slot[oc] >= 0
    keys = [point_clusters[op[on_free]] * nC + cam_slot[oc[on_free]]]
    values = [scores[on_free]]
    if len(both_idx):
        keys.append(point_clusters[op[both_idx]] * nC + both_camera)
        values.append(-np.einsum("ouk,ok->ou", Y, gp[both_point]))
    keys, values = np.concatenate(keys), np.concatenate(values)
    pairs, where = np.unique(keys, return_inverse=True)
    summed = np.zeros((len(pairs), n))
    np.add.at(summed, where.ravel(), values)
    _, cluster = np.unique(pairs // nC, return_inverse=True)
    cluster = cluster.ravel()
    G = int(cluster.max()) + 1 if len(cluster) else 0
    R = sparse.csr_matrix((summed.ravel(), (np.repeat(cluster, n), ((pairs % nC)[:, None] * n + np.arange(n)).ravel())),
                          shape=(G, nC * n))
    # about the clusters' mean share, as the jackknife's spread is about its mean: at a converged
    # solution their sum is zero; where the model is not one (the paper mode has no final BA),
    # the gradient they share is not a spread
    mean = np.asarray(R.sum(axis=0)).ravel() / max(G, 1)
    return ((R.T @ R).toarray() - G * np.outer(mean, mean)) * (G / max(G - 1, 1))


def camera_uncertainty(problem: BundleProblem, sigma_px: float | None = None,
                       groups: tuple[np.ndarray, np.ndarray] | None = None,
                       independent_cell_px: float | None = None,
                       point_clusters: np.ndarray | None = None) -> list[CameraUncertainty | None]:
    """The uncertainty of every free camera of ``problem`` at its solution (a converged
    :func:`stereoseed.estimators.bundle.bundle_adjust`'s cameras and points).

    sigma_px: the pixel noise (1 sigma, px, per image coordinate); None: estimated from the
    residuals, RSS / (2 n_obs - n_params) over the observations that enter the normal equations
    (meaningful at the solution: at the truth the RSS is not reduced by the fit).
    groups: cameras moved together by shared parameters (a stereo rig's stations: one pose per
    station, the rig held): (group (C,) int per camera of ``problem.Ps``, A (C, n, n): the camera's
    parameter increment = A @ its group's). The normal equations are then those of the groups'
    parameters (T^T S T) and each camera's covariance A Sigma_group A^T.
    independent_cell_px: the observations of a camera in one image cell of this size share the
    information of one observation (:func:`one_per_cell`); None: each is independent evidence.
    point_clusters: (M,) int, a cluster id per point of ``problem``: the covariance is also
    measured from the residuals, clusters of points independent, and the larger one reported
    (the module's docstring); None: the model's alone.
    Returns one entry per camera of ``problem.Ps`` (C,): None for a fixed camera, else a
    :class:`CameraUncertainty` (undetermined ones with infinite sigmas and a reason). Free
    cameras are first put in the model's family, as the BA does.
    """
    t0 = time.perf_counter()
    out: list[CameraUncertainty | None] = [None] * len(problem.Ps)
    free_cams = np.flatnonzero(problem.free_cameras)
    if len(free_cams) == 0:
        return out
    if sigma_px is not None and not (np.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"sigma_px must be a positive number of pixels, not {sigma_px!r}")
    camera_models.n_params(problem.model)  # an unknown model: its ValueError names the known ones
    model = CameraModel(problem.model)
    n, ni = model.n_params, model.n_intrinsics
    names = parameter_names(model)
    has_focal = ni > 0
    Ps = np.array(problem.Ps, dtype=np.float64, copy=True)
    X = np.ascontiguousarray(problem.points, dtype=np.float64)
    oc = np.asarray(problem.obs_camera, dtype=np.int64)
    op = np.asarray(problem.obs_point, dtype=np.int64)
    xy = np.asarray(problem.obs_xy, dtype=np.float64)
    free_pts = np.asarray(problem.free_points, dtype=bool)
    ref_Ks = None if problem.reference_K is None else np.asarray(problem.reference_K, np.float64)

    # each free camera's K R t and dP/dparams (analytic, the rotation as an increment about its axes)
    nC = len(free_cams)
    dP = np.empty((nC, n, 3, 4))
    ts = np.empty((nC, 3))
    for slot, c in enumerate(free_cams):
        ref = ref_Ks if ref_Ks is None or ref_Ks.ndim == 2 else ref_Ks[c]
        params, _ = camera_models.params_from_projection(Ps[c], model, ref)
        K, R, t = camera_models.krt_from_params(params, model, ref)
        Ps[c] = K @ np.hstack([R, t[:, None]])
        dP[slot] = camera_models.projection_derivatives(K, R, t, model, ref)
        ts[slot] = t
    is_free_cam = np.zeros(len(Ps), bool)
    is_free_cam[free_cams] = True

    # Only observations touching something free carry information; one of a point at infinity
    # (a non-finite residual) would make everything NaN.
    with np.errstate(all="ignore"):
        errors = observation_errors(Ps, X, oc, op, xy)
    relevant = is_free_cam[oc] | free_pts[op]
    keep = relevant & np.isfinite(errors)
    if (relevant & ~keep).any():
        log.warning("camera_uncertainty: %d observations with a non-finite residual left out", int((relevant & ~keep).sum()))
    usable = _usable_points(op[keep], oc[keep], free_pts, len(Ps))
    keep &= usable[op]

    cam_slot = np.full(len(Ps), -1, np.int64)
    cam_slot[free_cams] = np.arange(nC)
    for _ in range(2):  # a second pass only when a point's block turns out too ill-conditioned
        oc_k, op_k, xy_k = oc[keep], op[keep], xy[keep]
        weight_k = np.ones(len(oc_k)) if independent_cell_px is None else one_per_cell(oc_k, xy_k, independent_cell_px)
        pts = np.flatnonzero(free_pts & (np.bincount(op_k, minlength=len(X)) > 0))
        pt_slot = np.full(len(X), -1, np.int64)
        pt_slot[pts] = np.arange(len(pts))
        both = (cam_slot[oc_k] >= 0) & (pt_slot[op_k] >= 0)
        both_idx = np.flatnonzero(both)
        both_row = np.full(len(oc_k), -1, np.int64)
        both_row[both_idx] = np.arange(len(both_idx))
        U, gc, V, gp, W = normal_equations(Ps, X, oc_k, op_k, xy_k, weight_k, cam_slot, pt_slot, dP, np.inf, both_row,
                                            nC, len(pts), len(both_idx))
        ev = np.linalg.eigvalsh(V) if len(pts) else np.ones((0, 3))
        bad = ev[:, 0] < POINT_RCOND * ev[:, 2]
        if not bad.any():
            break
        log.debug("camera_uncertainty: %d points with a near-singular block (no parallax) left out", int(bad.sum()))
        keep &= ~np.isin(op, pts[bad])

    both_point, both_camera = pt_slot[op_k[both_idx]], cam_slot[oc_k[both_idx]]
    # grouped by point, then camera: the layout reduced_camera_matrix's kernel adds pairs in
    order, starts = pairs_by_point(both_point, both_camera)
    rows = thread_rows(order, starts, both_camera, nC)

    def reduced(U, V, gp, gc, W) -> tuple[np.ndarray, np.ndarray]:
        """(S (nC n, nC n), Y = W V^-1 per observation) of the normal equations' blocks."""
        Y = eliminate_points(V, gp, gc, W, 0.0, both_point, both_camera)[1]
        S = reduced_camera_matrix(order, starts, both_camera, np.swapaxes(W, 1, 2).copy(), Y, nC, rows)
        for i in range(nC):
            S[i * n:(i + 1) * n, i * n:(i + 1) * n] += U[i]
        return S, Y

    S, Y = reduced(U, V, gp, gc, W)

    def inverted(S: np.ndarray, meat: np.ndarray | None) -> tuple:
        """(blocks, determined, worst, n_weak, sandwich, n_blocks) of S, per camera or group."""
        if groups is None:
            return (*_inverse_camera_blocks(S, n, meat), nC)
        return _grouped_camera_blocks(S, n, free_cams, *groups, meat=meat)

    S_full, meat = S, None
    if point_clusters is not None:
        # the spread of the estimator the bundle adjustment runs: every observation at full
        # weight (the cell shares above are the model's count of independent evidence)
        point_clusters = np.asarray(point_clusters, np.int64)
        if len(point_clusters) != len(X):
            raise ValueError(f"point_clusters has {len(point_clusters)} entries for {len(X)} points")
        ones = np.ones(len(oc_k))
        if independent_cell_px is not None:
            U, gc, V, gp, W = normal_equations(Ps, X, oc_k, op_k, xy_k, ones, cam_slot, pt_slot, dP, np.inf,
                                                both_row, nC, len(pts), len(both_idx))
            S_full, Y = reduced(U, V, gp, gc, W)
        meat = _cluster_meat(Ps, X, oc_k, op_k, xy_k, ones, cam_slot, dP, gp, Y, both_idx, both_point,
                             both_camera, point_clusters, nC)
    t_built = time.perf_counter()
    # (one inversion when the model's weights are the adjustment's own)
    blocks, determined, worst, n_weak, sandwich, n_blocks = inverted(S, meat if S_full is S else None)
    if meat is not None and S_full is not S:
        sandwich = inverted(S_full, meat)[4]

    # The degrees of freedom: residuals minus the rank of J (the cameras' weak directions are
    # parameters the residuals do not see; every point kept has an invertible block).
    n_obs = len(oc_k)
    n_unknowns = n_blocks * n - n_weak + 3 * len(pts)
    dof = 2 * n_obs - n_unknowns
    if sigma_px is not None:
        sigma = float(sigma_px)
    elif dof > 0:
        sigma = float(np.sqrt(np.sum(errors[keep] ** 2) / dof))
    else:
        sigma = np.nan
    if sandwich is not None:
        # CR1's other factor (with _cluster_meat's G / (G - 1)): the cameras' parameters fitted
        # to the residuals. Not the points': each lies wholly in one cluster, whose share of the
        # reduced gradient has them eliminated already (fixed effects nested in the clusters)
        k_cams = n_blocks * n - n_weak
        sandwich = sandwich * ((2 * n_obs - 1) / (2 * n_obs - k_cams) if 2 * n_obs > k_cams else np.nan)
    cam_obs = np.bincount(oc_k, minlength=len(Ps))
    for slot, c in enumerate(free_cams):
        if not np.isfinite(sigma):
            out[c] = _undetermined(names, has_focal, sigma, f"no redundancy to estimate the pixel noise from: "
                                   f"{2 * n_obs} residuals for {n_unknowns} unknowns")
            continue
        if not determined[slot]:
            why = ("singular" if not np.isfinite(worst[slot]) or worst[slot] < 1e-14 else "ill-conditioned "
                   f"(weakest direction {worst[slot]:.1e} of the strongest)")
            out[c] = _undetermined(names, has_focal, sigma, f"normal equations {why} in this camera's parameters: "
                                   f"{int(cam_obs[c])} usable observations for {n} parameters (or the gauge is free)")
            continue
        cov = sigma ** 2 * 0.5 * (blocks[slot] + blocks[slot].T)
        J = _centre_jacobian(ts[slot], n)
        model_sigma = measured_sigma = None
        if sandwich is not None:
            model_sigma = _frozen(np.sqrt(np.maximum(np.diag(J @ cov @ J.T), 0.0)))
            measured_sigma = _frozen(np.sqrt(np.maximum(np.diag(J @ sandwich[slot] @ J.T), 0.0)))
            if measured_sigma.max() > model_sigma.max():  # the larger by the flags' measure, its worst axis
                cov = 0.5 * (sandwich[slot] + sandwich[slot].T)
        pos_cov = J @ cov @ J.T
        # the rotation and focal length: the larger of the two on each (the worst axis chose
        # the position's)
        spread = np.diag(cov) if sandwich is None else np.maximum(np.diag(cov), np.diag(sigma ** 2 * blocks[slot]))
        out[c] = CameraUncertainty(
            _frozen(np.sqrt(np.maximum(np.diag(pos_cov), 0.0))),
            _frozen(np.degrees(np.sqrt(np.maximum(spread[ni:ni + 3], 0.0)))),
            float(np.sqrt(max(spread[0], 0.0))) if has_focal else None,
            _frozen(cov), _frozen(pos_cov), names, sigma, model_position_sigma=model_sigma,
            measured_position_sigma=measured_sigma)
    n_bad = int((~determined).sum())
    if n_bad:
        log.info("camera_uncertainty: %d of %d free cameras undetermined", n_bad, nC)
    log.debug("camera_uncertainty: %d cameras, %d points, %d observations, sigma %.3g px: %.3f s to form S, "
              "%.3f s to invert", nC, len(pts), n_obs, sigma, t_built - t0, time.perf_counter() - t_built)
    return out
