"""Generalised resection: the pose of a stereo rig's station from the 2D-3D pairs of both its
cameras at once.

A rig is two cameras joined rigidly (:class:`Rig`): the first (left) camera K_left [R | t], the
second K_right [R_rl R | R_rl t + t_rl], where (R_rl, t_rl) maps the left camera's frame to the
right camera's (``X_right = R_rl X_left + t_rl``, as :class:`stereoseed.calibration.rig.RigResult`
gives it). A station's pose is the left camera's ``cam_from_world`` (R, t); the rig and the
intrinsics are known, so 6 numbers place both cameras, and every pair of either camera counts.

How (:func:`resect_rig`):

1. RANSAC over minimal samples: three pairs of one camera, P3P with that camera's K (OpenCV's
   AP3P, Ke & Roumeliotis 2017), each of its up to four poses carried to the left camera through
   the rig. The cameras take turns, so a station that one camera sees badly (or not at all) is
   placed by the other. Every hypothesis is scored with the pairs of both cameras, each by its own
   camera's reprojection error, in front of that camera (count, ties by the MSAC cost, Torr &
   Zisserman 2000); adaptive stopping on the better camera's inlier ratio (HZ §4.7.1).
2. Levenberg-Marquardt on the joint reprojection error of the inliers of both cameras (a rotation
   increment and the translation; Huber on each pair's 2D error, as the bundle adjustment does),
   inliers chosen again, twice; then least squares on the final inliers.

A failure is a value (:class:`RigResectionResult` with ``success`` False and its ``reason``); only
malformed input raises :class:`StereoseedError`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.estimators.bundle import damped_step
from stereoseed.estimators.config import BundleConfig, ResectionConfig
from stereoseed.estimators.robust import huber_cost, huber_weights
from stereoseed.arrays import read_only_float64
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.models import rotation_from_vector
from stereoseed.geometry.projection import compose_projection
from stereoseed.validation import positive, whole

log = logging.getLogger(__name__)

__all__ = ["Rig", "RigResectionConfig", "RigResectionResult", "resect_rig", "rig_reprojection_errors"]

_SIDES = ("left", "right")


@dataclass(frozen=True, eq=False)
class Rig:
    """A calibrated stereo rig: K_left, K_right (3, 3) and the right camera's pose in the left
    camera's frame, R_rl (3, 3), t_rl (3,): ``X_right = R_rl X_left + t_rl`` (the rig's unit is
    the world's: ``|t_rl|`` is the baseline). Arrays are stored read-only, each K scaled to
    K[2, 2] = 1."""

    K_left: np.ndarray
    K_right: np.ndarray
    R_rl: np.ndarray
    t_rl: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("K_left", (3, 3)), ("K_right", (3, 3)), ("R_rl", (3, 3)), ("t_rl", (3,))):
            a = np.asarray(getattr(self, name), np.float64)
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise StereoseedError(f"rig: {name} must be {shape} finite numbers, got shape {a.shape}; "
                                      f"check the calibration")
            object.__setattr__(self, name, read_only_float64(a))
        for name in ("K_left", "K_right"):
            K = np.array(getattr(self, name))
            lower = np.abs(K[np.tril_indices(3, -1)])
            if not (K[2, 2] > 0 and K[0, 0] / K[2, 2] > 0 and K[1, 1] / K[2, 2] > 0
                    and np.all(lower <= 1e-9 * abs(K[0, 0]))):
                raise StereoseedError(f"rig: {name} is not an intrinsic matrix (upper triangular, positive focal "
                                      f"lengths); check the calibration")
            K[np.tril_indices(3, -1)] = 0.0  # a decomposition's rounding: the pixels are computed from (0, 0, 1)
            object.__setattr__(self, name, read_only_float64(K / K[2, 2]))
        R = self.R_rl
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
            raise StereoseedError("rig: R_rl is not a rotation (orthonormal, determinant +1); check the calibration")
        # the RANSAC's and the BA's inner loops index the two Ks by side: stacked once
        object.__setattr__(self, "_Ks", read_only_float64(np.stack([self.K_left, self.K_right])))

    @classmethod
    def from_projections(cls, P_left: np.ndarray, P_right: np.ndarray) -> Rig:
        """The rig of a calibrated pair of cameras P_left, P_right (3, 4) taken together (the
        first station): both decomposed (:class:`~stereoseed.geometry.camera.Camera`), the right
        camera's pose related to the left's."""
        K_l, R_l, t_l = Camera(P_left).krt
        K_r, R_r, t_r = Camera(P_right).krt
        R_rl = R_r @ R_l.T
        return cls(K_l, K_r, R_rl, t_r - R_rl @ t_l)

    @property
    def baseline(self) -> float:
        """Distance between the two camera centres, in the world's unit."""
        return float(np.linalg.norm(self.t_rl))

    @property
    def Ks(self) -> np.ndarray:
        """(2, 3, 3): K_left, K_right, indexed by side (read-only)."""
        return self._Ks

    def right_pose(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The right camera's (R, t) at the station whose left camera is (R (3, 3), t (3,))."""
        return self.R_rl @ R, self.R_rl @ np.asarray(t, np.float64) + self.t_rl

    def left_pose(self, side: int, R_side: np.ndarray, t_side: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The station's (left camera's) pose from camera ``side``'s (R, t): the inverse of
        :meth:`right_pose` for side 1, the pose itself for side 0."""
        if side == 0:
            return np.asarray(R_side, np.float64), np.asarray(t_side, np.float64)
        return self.R_rl.T @ R_side, self.R_rl.T @ (np.asarray(t_side, np.float64) - self.t_rl)

    def projections(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The station's P_left, P_right (3, 4) for the left camera's pose (R, t)."""
        return compose_projection(self.K_left, R, t), compose_projection(self.K_right, *self.right_pose(R, t))


@dataclass(frozen=True)
class RigResectionConfig:
    # a pair is an inlier within this distance of its camera's reprojection: the resection's
    # (paper.md: "6-point DLT in RANSAC, 2 px")
    ransac_threshold_px: float = ResectionConfig.ransac_threshold_px
    ransac_confidence: float = ResectionConfig.ransac_confidence  # the resection's adaptive stopping
    # P3P samples are small (3 pairs): 30 % outliers need ~20 samples at 0.999, 60 % ~110; the
    # cap bounds a hopeless station's cost
    ransac_max_iters: int = 1000
    # below this many inliers (both cameras together) the station is reported as failed: the
    # single-camera resection's limit, so a rig station needs no more evidence than an image
    min_inliers: int = ResectionConfig.min_inliers
    max_rms_px: float = ResectionConfig.max_rms_px  # "wild reprojection error" guard after refinement
    # the robust refinement's Huber threshold on each pair's 2D error: the bundle adjustment's
    huber_px: float = BundleConfig.huber_px
    # LM steps per refinement: 6 unknowns from a P3P start converge in 3-6; the cap only guards a
    # start far off
    lm_iterations: int = 30
    seed: int = 0

    def __post_init__(self) -> None:
        positive(self, "ransac_threshold_px", "max_rms_px", "huber_px")
        whole(self, "ransac_max_iters", "lm_iterations")
        whole(self, "min_inliers", minimum=3)
        whole(self, "seed", minimum=0)
        if not 0.0 < self.ransac_confidence < 1.0:
            raise ValueError(f"RigResectionConfig.ransac_confidence must be within (0, 1), got {self.ransac_confidence!r}")


@dataclass(frozen=True, eq=False)
class RigResectionResult:
    """A station's pose from :func:`resect_rig`.

    success: whether the pose can be used; reason: why not (None on success). R (3, 3), t (3,):
    the left camera's ``cam_from_world`` (None when no hypothesis was found; on another failure the
    rejected estimate); inliers (N,) bool over the input pairs; rms_px over the inliers of both
    cameras; n_inliers (left, right); n_hypotheses: P3P samples tried; rig: the rig used.
    """

    success: bool
    reason: str | None
    R: np.ndarray | None
    t: np.ndarray | None
    inliers: np.ndarray
    rms_px: float
    n_inliers: tuple[int, int]
    n_hypotheses: int
    rig: Rig = field(repr=False)

    def projections(self) -> tuple[np.ndarray, np.ndarray]:
        """The station's P_left, P_right (3, 4); the right one has the rig's relative pose exactly.
        Raises ValueError on a result without a pose."""
        if self.R is None or self.t is None:
            raise ValueError(f"no station pose: {self.reason}")
        return self.rig.projections(self.R, self.t)

    @property
    def centre(self) -> np.ndarray | None:
        """The left camera's centre (3,), or None."""
        return None if self.R is None else -self.R.T @ self.t


def _check_input(points3d: np.ndarray, points2d: np.ndarray, side: np.ndarray, what: str
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    X = np.asarray(points3d, np.float64)
    x = np.asarray(points2d, np.float64)
    s = np.asarray(side)
    if X.ndim != 2 or X.shape[1] != 3:
        raise StereoseedError(f"{what}: 3D points must have shape (N, 3), got {X.shape}")
    if x.shape != (len(X), 2):
        raise StereoseedError(f"{what}: {len(X)} 3D points need pixels of shape ({len(X)}, 2), got {x.shape}")
    if s.shape != (len(X),) or not np.all(np.isin(s, (0, 1))):
        raise StereoseedError(f"{what}: side must give 0 (left) or 1 (right) for each of the {len(X)} pairs")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(x))):
        raise StereoseedError(f"{what}: NaN or infinite coordinates; remove those pairs")
    return X, x, s.astype(np.int64)


def _camera_points(rig: Rig, R: np.ndarray, t: np.ndarray, X: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Each point (N, 3) in the frame of the camera that sees it: (N, 3)."""
    Y = X @ R.T + t
    right = side == 1
    Y[right] = Y[right] @ rig.R_rl.T + rig.t_rl
    return Y


def _pixels(rig: Rig, Y: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points Y (N, 3), each through its side's K."""
    K = rig.Ks[side]  # (N, 3, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = Y[:, :2] / Y[:, 2:3]
    return np.einsum("nij,nj->ni", K[:, :2, :2], n) + K[:, :2, 2]


def rig_reprojection_errors(rig: Rig, R: np.ndarray, t: np.ndarray, points3d: np.ndarray, points2d: np.ndarray,
                            side: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection distance (N,) px of each pair in its side's camera at the station (R, t), and
    whether the point lies in front of that camera (N,) bool."""
    side = np.asarray(side, np.int64)
    Y = _camera_points(rig, R, np.asarray(t, np.float64), np.asarray(points3d, np.float64), side)
    err = np.linalg.norm(_pixels(rig, Y, side) - points2d, axis=1)
    return err, Y[:, 2] > 0


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """[v]_x of each row of v (N, 3): (N, 3, 3)."""
    S = np.zeros(v.shape[:1] + (3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def _residuals_jacobian(rig: Rig, R: np.ndarray, t: np.ndarray, X: np.ndarray, x: np.ndarray, side: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals r (N, 2) and their Jacobian (N, 2, 6) with respect to a rotation increment w
    (R <- exp([w]x) R, at w = 0) and t."""
    RX = X @ R.T
    Y = RX + t
    dY = np.concatenate([-_skew_rows(RX), np.broadcast_to(np.eye(3), (len(X), 3, 3))], axis=2)  # (N, 3, 6)
    right = side == 1
    Y[right] = Y[right] @ rig.R_rl.T + rig.t_rl
    dY[right] = np.einsum("ij,njk->nik", rig.R_rl, dY[right])
    K = rig.Ks[side]
    z = Y[:, 2]
    dn = np.zeros((len(X), 2, 3))  # d(Y1/Y3, Y2/Y3)/dY
    dn[:, 0, 0] = dn[:, 1, 1] = 1.0 / z
    dn[:, 0, 2] = -Y[:, 0] / z ** 2
    dn[:, 1, 2] = -Y[:, 1] / z ** 2
    r = np.einsum("nij,nj->ni", K[:, :2, :2], Y[:, :2] / z[:, None]) + K[:, :2, 2] - x
    J = np.einsum("nij,njk,nkl->nil", K[:, :2, :2], dn, dY)
    return r, J


def _refine(rig: Rig, R: np.ndarray, t: np.ndarray, X: np.ndarray, x: np.ndarray, side: np.ndarray,
            delta: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on the (Huber, ``delta`` px on each pair's 2D error; inf: least
    squares) reprojection error of the pairs of both cameras over the station's 6 pose parameters."""
    lam = 1e-3
    r, J = _residuals_jacobian(rig, R, t, X, x, side)
    cost = huber_cost(r, delta)
    for _ in range(iterations):
        w = huber_weights(np.linalg.norm(r, axis=1), delta)
        H = np.einsum("nai,n,naj->ij", J, w, J)
        g = np.einsum("nai,n,na->i", J, w, r)

        def trial(lam: float) -> tuple[tuple, float]:  # called at once by damped_step, in this iteration
            step = np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-12 * np.eye(6), -g)
            R_new = rotation_from_vector(step[:3]) @ R
            t_new = t + step[3:]
            r_new, J_new = _residuals_jacobian(rig, R_new, t_new, X, x, side)
            with np.errstate(invalid="ignore"):
                return (R_new, t_new, r_new, J_new), huber_cost(r_new, delta)

        state, cost, lam, gain = damped_step(trial, cost, lam)
        if state is None:
            break
        R, t, r, J = state
        if gain < 1e-14:
            break
    return R, t


def _p3p(rig: Rig, s: int, X: np.ndarray, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The left camera's poses (R, t) of a P3P sample X (3, 3), x (3, 2) of camera ``s``."""
    K = rig.K_left if s == 0 else rig.K_right
    try:
        n, rvecs, tvecs = cv2.solveP3P(X, x, K, None, flags=cv2.SOLVEPNP_AP3P)
    except cv2.error:  # a degenerate sample (collinear points)
        return []
    poses = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        R_s, t_s = cv2.Rodrigues(np.asarray(rvec, np.float64))[0], np.asarray(tvec, np.float64).ravel()
        if np.all(np.isfinite(R_s)) and np.all(np.isfinite(t_s)):
            poses.append(rig.left_pose(s, R_s, t_s))
    return poses


def _ransac(rig: Rig, X: np.ndarray, x: np.ndarray, side: np.ndarray, config: RigResectionConfig
            ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray, int]:
    """The best P3P hypothesis (R, t) or (None, None), its inliers (N,) bool, samples tried."""
    rng = np.random.default_rng(config.seed)
    members = [np.flatnonzero(side == s) for s in (0, 1)]
    sides = [s for s in (0, 1) if len(members[s]) >= 3]
    thr2 = config.ransac_threshold_px ** 2
    Xc = np.ascontiguousarray(X)  # OpenCV takes contiguous samples
    best: tuple = (-1, np.inf, None, None, np.zeros(len(X), bool))
    stop_at = config.ransac_max_iters
    tried = 0
    while tried < stop_at:
        s = sides[tried % len(sides)]
        tried += 1
        sample = rng.choice(members[s], 3, replace=False)
        for R, t in _p3p(rig, s, Xc[sample], np.ascontiguousarray(x[sample])):
            err, front = rig_reprojection_errors(rig, R, t, X, x, side)
            err2 = np.where(front, err ** 2, np.inf)
            inliers = err2 < thr2
            count, msac = int(inliers.sum()), float(np.sum(np.minimum(err2, thr2)))
            if (count, -msac) > (best[0], -best[1]):
                best = (count, msac, R, t, inliers)
                needed = []
                for q in sides:
                    ratio = inliers[members[q]].mean()
                    denom = np.log(max(1e-12, 1.0 - ratio ** 3))  # 0 when no pair agrees: no bound
                    needed.append(np.log(1.0 - config.ransac_confidence) / denom if denom < 0 else np.inf)
                # the sides take turns: the better one is sampled every len(sides)-th time
                stop_at = int(min(config.ransac_max_iters, np.ceil(min(needed)) * len(sides)))
    return best[2], best[3], best[4], tried


def resect_rig(rig: Rig, points3d: np.ndarray, points2d: np.ndarray, side: np.ndarray,
               config: RigResectionConfig = RigResectionConfig(), what: str = "station") -> RigResectionResult:
    """The station's pose from 2D-3D pairs of both cameras of ``rig`` (module docstring).

    points3d (N, 3) world points; points2d (N, 2) their undistorted pixels; side (N,) 0 when the
    left camera saw the pair, 1 the right. Raises :class:`StereoseedError` on malformed input
    (``what`` names it); every other failure is a result with ``success`` False and its reason.
    """
    X, x, side = _check_input(points3d, points2d, side, what)
    n = len(X)
    per_side = (int(np.sum(side == 0)), int(np.sum(side == 1)))
    need = config.min_inliers

    def failed(reason: str, R=None, t=None, inliers=None, rms=np.inf, tried=0) -> RigResectionResult:
        inliers = np.zeros(n, bool) if inliers is None else inliers
        counts = (int(np.sum(inliers & (side == 0))), int(np.sum(inliers & (side == 1))))
        log.debug("%s: %s", what, reason)
        return RigResectionResult(False, f"{what}: {reason}", R, t, inliers, float(rms), counts, tried, rig)

    if n < need:
        return failed(f"{n} 2D-3D pairs ({per_side[0]} left, {per_side[1]} right), at least {need} are needed")
    if max(per_side) < 3:
        return failed(f"no camera has the 3 pairs of a minimal sample ({per_side[0]} left, {per_side[1]} right)")
    R, t, inliers, tried = _ransac(rig, X, x, side, config)
    if R is None or inliers.sum() < need:
        return failed(f"only {int(inliers.sum())} of {n} 2D-3D pairs agree on a station pose (need {need}); "
                      f"too few correct matches", R, t, inliers, tried=tried)
    thr = config.ransac_threshold_px
    for _ in range(2):  # refine, choose the inliers again: converges in one or two rounds
        R, t = _refine(rig, R, t, X[inliers], x[inliers], side[inliers], config.huber_px, config.lm_iterations)
        err, front = rig_reprojection_errors(rig, R, t, X, x, side)
        new = (err < thr) & front
        if new.sum() < need or np.array_equal(new, inliers):
            break
        inliers = new
    R, t = _refine(rig, R, t, X[inliers], x[inliers], side[inliers], np.inf, config.lm_iterations)
    err, front = rig_reprojection_errors(rig, R, t, X, x, side)
    inliers = inliers & front
    rms = float(np.sqrt(np.mean(err[inliers] ** 2))) if inliers.any() else np.inf
    if inliers.sum() < need:
        return failed(f"only {int(inliers.sum())} pairs stay in front of their camera after refinement (need {need})",
                      R, t, inliers, rms, tried)
    if not rms <= config.max_rms_px:
        return failed(f"the best pose reprojects its inliers with {rms:.2f} px RMS (limit {config.max_rms_px} px); "
                      f"the 2D-3D pairs are inconsistent", R, t, inliers, rms, tried)
    counts = (int(np.sum(inliers & (side == 0))), int(np.sum(inliers & (side == 1))))
    log.debug("%s: %d + %d inliers of %d pairs, %.3f px RMS, %d samples", what, *counts, n, rms, tried)
    return RigResectionResult(True, None, R, t, inliers, rms, counts, tried, rig)
