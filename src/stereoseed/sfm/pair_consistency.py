"""How well the calibrated pair agrees with the walk placed from it.

The final bundle adjustment holds the pair (it carries the metric frame), so the cameras'
covariance is relative to the pair, as if the pair were exact. Once the walk is placed, the run
can measure how far that holds: each camera of the pair is resected, its intrinsics held, from
the points as the *other* cameras triangulate them (its own observations left out). Where the
pair agrees with the walk it lands within its statistical uncertainty of where it is; where it
does not, the offset is what the images say against the calibration (a rig bumped or refocused
after it was calibrated, a calibration's own error, or a bias of the pair's observations).
report.json keeps it (``final.pair_consistency``); the benchmarks use the same resection on the
published cameras to measure the ground truth's own error (docs/benchmarks.md).
"""
from __future__ import annotations

from typing import Any, Iterable, Mapping

import numpy as np

from stereoseed.estimators.covariance import one_per_cell
from stereoseed.estimators.pose import PoseRefinement, refine_pose
from stereoseed.estimators.triangulation import triangulate_tracks
from stereoseed.geometry.models import rotation_from_vector
from stereoseed.geometry.projection import decompose_projection, skew
from stereoseed.scene.reconstruction import Reconstruction

__all__ = ["centre_offset", "left_out_pose", "pair_consistency"]

# a point enters the leave-one-out resection when at least this many other registered cameras
# see it: two rays fix it without the left-out camera
MIN_OTHER_VIEWS = 2
# a pair whose leave-one-out resection keeps fewer pairs than this says nothing about it
MIN_PAIRS = 12


def left_out_pose(recon: Reconstruction, view: int, cell_px: float | None, inlier_px: float,
                  cameras: Mapping[int, np.ndarray] | None = None) -> tuple[PoseRefinement, np.ndarray, np.ndarray] | None:
    """Camera ``view`` resected, its intrinsics held, from the points its observations see as
    the *other* registered cameras triangulate them (each seen by at least two of them): its
    refinement from where it is (:class:`~stereoseed.estimators.pose.PoseRefinement`) and its
    R (3, 3), t (3,). ``cameras``: {view: P (3, 4)} to use instead of the run's own (a
    benchmark's published cameras); observations counted once per ``cell_px`` cell of the
    image (None: each independent, as the cameras' covariance takes it), pairs beyond
    ``inlier_px`` at the refined pose left out. None when fewer than
    :data:`MIN_PAIRS` pairs remain or the resection fails."""
    Ps = {o: recon.views[o].P for o in recon.registered_views} if cameras is None else dict(cameras)
    if Ps.get(view) is None:
        return None
    others = np.array([o for o in recon.registered_views if o != view and Ps.get(o) is not None], np.int64)
    alive = recon.alive[recon.obs_point]
    mine = (recon.obs_view == view) & alive
    points = np.unique(recon.obs_point[mine])
    rest = alive & np.isin(recon.obs_view, others) & np.isin(recon.obs_point, points)
    seen = np.bincount(recon.obs_point[rest], minlength=len(recon.alive))
    points = points[seen[points] >= MIN_OTHER_VIEWS]
    if len(points) < MIN_PAIRS:
        return None
    rest &= np.isin(recon.obs_point, points)
    slot = np.full(len(recon.alive), -1, np.int64)
    slot[points] = np.arange(len(points))
    P_obs = np.stack([Ps[int(o)] for o in recon.obs_view[rest]])
    X = triangulate_tracks(P_obs, recon.observation_xy(rest), slot[recon.obs_point[rest]], len(points))
    mine &= np.isin(recon.obs_point, points)
    X_mine = X[slot[recon.obs_point[mine]]]
    xy = recon.observation_xy(mine)
    ok = np.isfinite(X_mine).all(axis=1)
    if ok.sum() < MIN_PAIRS:
        return None
    K, R, t = decompose_projection(Ps[view])
    weights = None if cell_px is None else one_per_cell(np.zeros(int(ok.sum()), np.int64), xy[ok], cell_px)
    found = refine_pose(K, R, t, X_mine[ok], xy[ok], weights, inlier_px=inlier_px)
    if found is None or found.n_used < MIN_PAIRS:
        return None
    return found, R, t


def centre_offset(R: np.ndarray, t: np.ndarray, found: PoseRefinement) -> tuple[float, float]:
    """(how far the refinement moved the camera centre, its 1-sigma along the worst axis)."""
    w, dt = found.increment[:3], found.increment[3:]
    R1 = rotation_from_vector(w) @ R
    moved = float(np.linalg.norm(-R1.T @ (t + dt) + R.T @ t))
    J = -R.T @ np.hstack([skew(t), np.eye(3)])  # dC = -R^T (dt + [t]x w) to first order
    sigma = float(np.sqrt(max(np.linalg.eigvalsh(J @ found.covariance @ J.T)[-1], 0.0)))
    return moved, sigma


def pair_consistency(recon: Reconstruction, views: Iterable[int], cell_px: float | None, inlier_px: float,
                     cameras: Mapping[int, np.ndarray] | None = None) -> dict[str, Any]:
    """{image name: {"offset": how far the rest of the walk puts the camera's centre from where
    the calibration does, "sigma": that resection's own 1-sigma (worst axis), "rotation_mrad":
    how far it turns it, "pairs": the 3D-2D pairs it rests on}} for the ``views`` (the
    calibrated pair) the walk can measure (:func:`left_out_pose`, ``cameras`` as there)."""
    out = {}
    for view in views:
        found = left_out_pose(recon, view, cell_px, inlier_px, cameras)
        if found is None:
            continue
        moved, sigma = centre_offset(found[1], found[2], found[0])
        out[recon.views[view].name] = {"offset": moved, "sigma": sigma, "pairs": found[0].n_used,
                                       "rotation_mrad": 1e3 * float(np.linalg.norm(found[0].increment[:3]))}
    return out
