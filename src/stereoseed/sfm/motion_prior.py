"""3D-2D correspondences without epipolar geometry: the camera predicted from the previous
motion, the recent points paired with the interest points near their predicted pixels.

Used where the chain from I_{k-1} <-> I_k is missing or weak (repeated patterns, little
texture, docs/mapper.md). A repeated pattern offers several consistent pairings (the
prediction shifted by one period), so this module returns *hypotheses*; the registration
resects each and keeps the camera that explains the most recent points (:func:`explained_points`).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from stereoseed.geometry.camera import Camera
from stereoseed.arrays import unique
from stereoseed.geometry.projection import project
from stereoseed.estimators.config import ResectionConfig
from stereoseed.sfm.config import MotionPriorConfig
from stereoseed.features.harris import Features
from stereoseed.geometry.neighbours import nearest_within
from stereoseed.scene.reconstruction import Reconstruction

__all__ = ["pose_matrix", "predict_pose", "predict_camera", "recent_points", "described_points", "hypotheses_by_motion_prior", "explained_points", "explaining_matches", "Hypothesis",
           "trusted_chain_inliers"]


@dataclass(frozen=True)
class Hypothesis:
    """One consistent set of 3D-2D correspondences: points3d (N, 3), points2d (N, 2), their
    ZNCC scores (N,), and where it came from: the search radius (fraction of the image width)
    and the number of best pairings per point it was drawn from."""

    points3d: np.ndarray
    points2d: np.ndarray
    scores: np.ndarray
    radius_fraction: float
    pairings_per_point: int

    def __len__(self) -> int:
        return len(self.points3d)


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4 x 4 cam_from_world matrix of rotation R (3, 3) and translation t (3,)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def predict_pose(T_before: np.ndarray, T_last: np.ndarray, steps: int = 1) -> np.ndarray:
    """Constant motion: the rigid motion from pose ``T_before`` to ``T_last`` (4 x 4
    cam_from_world) applied ``steps`` (at least one) more times to ``T_last``. -> (4, 4)."""
    T_next = T_last
    for _ in range(max(1, steps)):
        T_next = T_last @ np.linalg.inv(T_before) @ T_next
    return T_next


def predict_camera(P_before: np.ndarray, P_last: np.ndarray, steps: int = 1) -> np.ndarray:
    """Constant-motion prediction of a later camera (:func:`predict_pose`) from ``P_before`` and
    ``P_last`` (both (3, 4)), with ``P_last``'s intrinsics. -> (3, 4)."""
    _, R_before, t_before = Camera(P_before).krt
    K, R_last, t_last = Camera(P_last).krt
    return K @ predict_pose(pose_matrix(R_before, t_before), pose_matrix(R_last, t_last), steps)[:3]


def trusted_chain_inliers(motion_prior: MotionPriorConfig, resection: ResectionConfig) -> int:
    """Resection inliers an epipolar chain needs to be trusted without the motion prior
    (``MotionPriorConfig.trusted_chain_factor`` x ``ResectionConfig.min_inliers``, rounded up):
    fewer, and the quasi-dense attempt runs; fewer ties after the final BA, and a camera is weak."""
    return int(np.ceil(motion_prior.trusted_chain_factor * resection.min_inliers))


def recent_points(recon: Reconstruction, prev: int, n_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Live points seen in the last ``n_views`` registered views up to ``prev``, each described
    by its patch in the latest of them: (point ids (N,), descriptors (N, D) float32)."""
    recent = [prev] + recon.registered_before(prev, n_views - 1)
    sel = np.isin(recon.obs_view, recent) & recon.alive[recon.obs_point]
    return described_points(recon, np.flatnonzero(sel)[np.argsort(-recon.obs_view[sel], kind="stable")], prev)


def described_points(recon: Reconstruction, rows: np.ndarray, view: int) -> tuple[np.ndarray, np.ndarray]:
    """The points of the observations ``rows`` (R,), each described by its patch at the first of
    its rows: (point ids (N,), descriptors (N, D) float32, D that of ``view``'s)."""
    pids, first = np.unique(recon.obs_point[rows], return_index=True)
    obs = rows[first]
    desc = np.zeros((len(obs), recon.views[view].features.desc.shape[1]), np.float32)
    for v in unique(recon.obs_view[obs]):
        here = recon.obs_view[obs] == v
        desc[here] = recon.views[v].features.desc[recon.obs_feature[obs[here]]]
    return pids, desc


def hypotheses_by_motion_prior(recon: Reconstruction, prev: int, k: int, features: Features,
                               motion_prior: MotionPriorConfig, resection: ResectionConfig,
                               recent: tuple[np.ndarray, np.ndarray]) -> list[list[Hypothesis]]:
    """Correspondences for view k (its interest points ``features``) from the predicted camera.

    The points ``recent`` (from :func:`recent_points`) are projected with the camera predicted
    from the last two registered views (:func:`predict_camera`); every interest point of k
    within a radius (``MotionPriorConfig.radius_fractions`` of the image width) whose patch
    matches (ZNCC >= ``min_zncc``, among the point's best ``pairings_per_point``) is a pairing,
    and a robust 2D similarity between predicted and found positions keeps the consistent ones
    (the resection's RANSAC follows): the prediction misses mostly by a zoom about the
    principal point and a shift. Up to ``hypotheses_per_search`` similarities are found one
    after another on the pairings the previous ones left, best supported first.

    Returns one list of hypotheses per search radius; empty lists without a motion to
    extrapolate (no registered view before ``prev``) or with fewer than 4 recent points.
    """
    mp = motion_prior
    before = recon.registered_before(prev, 1)
    if not before:
        return [[] for _ in mp.radius_fractions]
    # images skipped since (failed insertions) count as steps of the same motion
    steps = max(1, round((k - prev) / max(prev - before[0], 1)))
    return hypotheses_near(recon, predict_camera(recon.views[before[0]].P, recon.views[prev].P, steps), features,
                           motion_prior, resection, recent)


def hypotheses_near(recon: Reconstruction, P_pred: np.ndarray, features: Features, motion_prior: MotionPriorConfig,
                    resection: ResectionConfig, recent: tuple[np.ndarray, np.ndarray]) -> list[list[Hypothesis]]:
    """:func:`hypotheses_by_motion_prior`'s search around the projections of the ``recent``
    points by a predicted camera ``P_pred`` (3, 4): one list of hypotheses per search radius
    (empty lists with fewer than a resection's points)."""
    mp = motion_prior
    none: list[list[Hypothesis]] = [[] for _ in mp.radius_fractions]
    pids, desc = recent
    if len(pids) < resection.min_points or len(features) == 0:
        return none
    pred = project(P_pred, recon.points[pids])
    width = features.image_shape[1]
    # the distances as norm(axis=2) computes them, without the (N, M, 2) array
    dx = pred[:, 0, None] - features.points[None, :, 0]
    dy = pred[:, 1, None] - features.points[None, :, 1]
    d = np.sqrt(dx * dx + dy * dy)
    zncc_all = desc @ features.desc.T
    zncc_all[:, ~features.valid] = -np.inf
    out = []
    deepest = min(max(mp.pairings_per_point), zncc_all.shape[1])
    for radius_fraction in mp.radius_fractions:
        zncc = np.where(d > radius_fraction * width, -np.inf, zncc_all)
        # each point's best pairings, best first: the top few partitioned out, then sorted (a
        # full sort of every row cost most of the search)
        top = np.argpartition(-zncc, deepest - 1, axis=1)[:, :deepest] if deepest < zncc.shape[1] else \
            np.broadcast_to(np.arange(zncc.shape[1]), zncc.shape)
        ranked = np.take_along_axis(top, np.argsort(-np.take_along_axis(zncc, top, axis=1), axis=1, kind="stable"),
                                    axis=1)
        hypotheses = []
        for depth in mp.pairings_per_point:
            rows = np.repeat(np.arange(len(pids)), min(depth, ranked.shape[1]))
            cols = ranked[:, :depth].ravel()
            ok = zncc[rows, cols] >= mp.min_zncc
            found = _similarities(pred, features.points, rows[ok], cols[ok], zncc, mp, resection, width)
            hypotheses += [Hypothesis(recon.points[pids[r]], x, z, radius_fraction, depth) for r, x, z in found]
        out.append(hypotheses)
    return out


def _similarities(pred: np.ndarray, xy: np.ndarray, rows: np.ndarray, cols: np.ndarray, zncc: np.ndarray,
                  mp: MotionPriorConfig, rc: ResectionConfig, width: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Robust 4-DOF similarities (2-point samples, so a low inlier ratio is fine) between the
    predicted pixels ``pred[rows]`` and the paired interest points ``xy[cols]``, one after
    another on what the previous ones left; each keeps one pairing per point (the closest to
    the similarity); a similarity supported by fewer pairings than a resection needs
    (``ResectionConfig.min_points``) ends the search. Returns (rows (K,) into pred, pixels (K, 2),
    scores (K,)) per similarity."""
    hypotheses = []
    while len(rows) >= rc.min_points and len(hypotheses) < mp.hypotheses_per_search:
        x = xy[cols]
        # OpenCV's RANSAC registrator seeds its own generator: deterministic without cv2.setRNGSeed
        S, inl = cv2.estimateAffinePartial2D(pred[rows], x, method=cv2.RANSAC,
                                             ransacReprojThreshold=mp.similarity_threshold * width,
                                             maxIters=mp.similarity_max_iters, confidence=rc.ransac_confidence)
        if S is None or inl is None or inl.sum() < rc.min_points:
            break
        inl = np.flatnonzero(inl.ravel())
        err = np.linalg.norm(pred[rows[inl]] @ S[:, :2].T + S[:, 2] - x[inl], axis=1)
        order = inl[np.argsort(err)]
        _, first = np.unique(rows[order], return_index=True)
        sel = order[first]
        hypotheses.append((rows[sel], x[sel], zncc[rows[sel], cols[sel]]))
        rest = np.ones(len(rows), bool)
        rest[inl] = False
        rows, cols = rows[rest], cols[rest]
    return hypotheses


def _patch_matches(features: Features, projections: np.ndarray, desc: np.ndarray, max_px: float,
                   min_zncc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``projections`` (M, 2) of points described by ``desc`` (N, D) (row r: point r mod N;
    M a multiple of N, a block per camera) that an interest point within ``max_px`` explains, its
    patch matching (ZNCC >= ``min_zncc``): (rows (K,), interest points (K,), ZNCC (K,)). One grid
    of the interest points for every row; a projection that is not finite finds none."""
    dist, nearest = nearest_within(features.points, projections, max_px)
    close = np.flatnonzero(np.isfinite(dist))
    zncc = np.einsum("nd,nd->n", desc[close % len(desc)], features.desc[nearest[close]])
    ok = zncc >= min_zncc
    return close[ok], nearest[close[ok]], zncc[ok]


def explaining_matches(features: Features, P: np.ndarray, points: np.ndarray, desc: np.ndarray,
                       max_px: float, min_zncc: float) -> tuple[np.ndarray, np.ndarray]:
    """The matches behind :func:`explained_points` for one camera P (3, 4): (rows of ``points``
    (K,), the interest points explaining them (K,)), an interest point explaining one point at
    most (the best matching patch; :func:`explained_points` counts every point)."""
    rows, feats, zncc = _patch_matches(features, project(P, points), desc, max_px, min_zncc)
    order = np.argsort(-zncc, kind="stable")
    _, first = np.unique(feats[order], return_index=True)
    keep = np.sort(order[first])
    return rows[keep], feats[keep]


def explained_points(features: Features, cameras: list[np.ndarray], points: np.ndarray, desc: np.ndarray,
                     max_px: float, min_zncc: float) -> np.ndarray:
    """How many of the recent ``points`` (N, 3), described by their patches ``desc`` (N, D),
    each camera (3, 4) explains in a view with interest points ``features``: a point counts
    when an interest point within ``max_px`` of its projection matches its patch (ZNCC >=
    ``min_zncc``). A camera shifted by one period of a repeated pattern explains its own
    correspondences as well as the true one, but loses the points at the pattern's ends and
    everything else in view. -> (len(cameras),) int64."""
    n = len(points)
    if n == 0 or not cameras:
        return np.zeros(len(cameras), np.int64)
    # every camera's projections in one search
    rows, _, _ = _patch_matches(features, np.concatenate([project(P, points) for P in cameras]), desc, max_px, min_zncc)
    return np.bincount(rows // n, minlength=len(cameras)).astype(np.int64)
