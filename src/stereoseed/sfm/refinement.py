"""Bundle adjustment of a part of the reconstruction (paper §4.3, eq. 12) and outlier removal.

:func:`adjust` builds a :class:`~stereoseed.estimators.bundle.BundleProblem` from chosen free views and
points; :func:`drop_outliers` removes the observations the adjusted model cannot explain;
:func:`global_adjust` alternates the two over every registered view, as COLMAP's global BA.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from stereoseed.arrays import unique
from stereoseed.estimators.bundle import BundleProblem, bundle_adjust
from stereoseed.estimators.config import BundleConfig
from stereoseed.geometry.camera_model import CameraModel
from stereoseed.sfm.config import OutlierConfig
from stereoseed.scene.reconstruction import Reconstruction, eq14

__all__ = ["adjust", "ba_report", "bundle_problem", "drop_outliers", "global_adjust", "select_tracks"]

CALIBRATED = (0, 1)  # the calibrated pair fixes the frame and the scale: it never moves


def ba_report(result: dict[str, Any] | None) -> dict[str, Any]:
    """The JSON-able report of an :func:`adjust` (``{"skipped": True}`` when it had nothing to adjust)."""
    return {"skipped": True} if result is None else result


def bundle_problem(recon: Reconstruction, model: CameraModel, free_views: list[int],
                   free_points: np.ndarray | None = None, views_in_cost: list[int] | None = None,
                   points_in_cost: np.ndarray | None = None) -> tuple[BundleProblem, np.ndarray, np.ndarray] | None:
    """The bundle adjustment problem of :func:`adjust` (same arguments; ``model``: the run's camera
    model, ``PipelineConfig.camera_model`` resolved, or "fixed" when the BA holds the intrinsics),
    with the views and the points it involves ((C,), (M,) ids); None when no observation is involved."""
    free_views = [v for v in free_views if v not in CALIBRATED]
    in_free_views = np.isin(recon.obs_view, free_views)
    if free_points is None:
        free_points = unique(recon.obs_point[in_free_views])
    involved = np.isin(recon.obs_point, free_points) | in_free_views
    if views_in_cost is not None:
        involved &= np.isin(recon.obs_view, views_in_cost)
    if points_in_cost is not None:
        involved &= np.isin(recon.obs_point, points_in_cost)
    involved &= recon.alive[recon.obs_point]
    if not involved.any():
        return None
    # One model for every free camera of a BA: a view that needed a constrained model (its
    # 11-DOF camera was refused) is adjusted with it when it is free alone, and held fixed when
    # it is free together with cameras of the run's model.
    run_model = model
    model_of = {v: recon.views[v].camera_model or run_model for v in free_views}
    models = set(model_of.values())
    model = models.pop() if len(models) == 1 else run_model
    free_views = [v for v in free_views if model_of[v] == model]
    cams = unique(recon.obs_view[involved])
    pts = unique(recon.obs_point[involved])
    problem = BundleProblem(
        Ps=np.stack([recon.views[v].P for v in cams]),
        free_cameras=np.isin(cams, free_views),
        points=recon.points[pts],
        free_points=np.isin(pts, free_points),
        obs_camera=np.searchsorted(cams, recon.obs_view[involved]),
        obs_point=np.searchsorted(pts, recon.obs_point[involved]),
        obs_xy=recon.observation_xy(involved),
        model=model,
        reference_K=np.stack([recon.reference_K(v) for v in cams]),
        cameras=[recon.views[v].camera for v in cams],
    )
    return problem, cams, pts


def adjust(recon: Reconstruction, bundle: BundleConfig, model: CameraModel, free_views: list[int],
           free_points: np.ndarray | None = None, views_in_cost: list[int] | None = None,
           points_in_cost: np.ndarray | None = None) -> dict[str, Any] | None:
    """Bundle-adjust with ``free_views`` free; points free = ``free_points`` or, by default,
    every point those views observe; the cost holds every observation of the involved points
    (in ``views_in_cost`` only, and of ``points_in_cost`` only, if given). Returns a JSON-able
    report, or None when there is nothing to adjust (no observation involved)."""
    built = bundle_problem(recon, model, free_views, free_points, views_in_cost, points_in_cost)
    if built is None:
        return None
    problem, cams, pts = built
    result = bundle_adjust(problem, bundle)
    for i, v in enumerate(cams):
        if problem.free_cameras[i]:
            recon.views[v].P = result.Ps[i]
    recon.points[pts] = result.points
    o = len(problem.obs_camera)
    rms_b, rms_a = result.rms_before, result.rms_after
    return {"free_cameras": int(problem.free_cameras.sum()), "free_points": int(problem.free_points.sum()),
            "observations": o, "iterations": result.iterations, "seconds": result.seconds,
            "rms_before_px": rms_b, "rms_after_px": rms_a,
            "eq14_before": eq14(rms_b ** 2 * o, len(cams), len(pts)),
            "eq14_after": eq14(rms_a ** 2 * o, len(cams), len(pts))}


def drop_outliers(recon: Reconstruction, outliers: OutlierConfig) -> int:
    """Remove the observations reprojecting beyond ``OutlierConfig.max_px`` and, with an
    outlier factor (``OutlierConfig.factor``), beyond that factor times the median
    error (never below ``OutlierConfig.floor_px``); then the points seen fewer than twice. Long
    tracks collect a few wrong observations (patches straddling an occlusion edge) that pull
    the chain one way. Returns the number of observations removed."""
    if len(recon.obs_view) == 0:
        return 0
    err = recon.observation_errors()
    threshold = outliers.max_px
    factor = outliers.active_factor()
    counted = np.isfinite(err) & recon.alive[recon.obs_point]
    if factor is not None and counted.any():
        relative = max(outliers.floor_px, factor * float(np.median(err[counted])))
        threshold = min(threshold, relative)
    return recon.filter_observations(err > threshold)


def global_adjust(recon: Reconstruction, bundle: BundleConfig, outliers: OutlierConfig, model: CameraModel,
                  adjust_everything: Callable[[Reconstruction, int], dict[str, Any] | None] | None = None
                  ) -> tuple[dict[str, Any], int]:
    """Bundle-adjust every registered view (the pair fixed), drop the outliers, and again while
    the last round removed more than ``BundleConfig.negligible_drop`` of the observations (at
    most ``global_rounds``): the wrong observations left by drift hold the first solution away
    from the right one. A large model (forming its reduced camera system costs more than
    ``BundleConfig.subset_above`` track-length² blocks) adjusts its cameras on the points of
    :func:`select_tracks` and then every other point with the cameras fixed. Returns (the last
    round's BA report with "rounds", "removed_per_round" and the first round's starting RMS
    added, observations removed). adjust_everything(recon, round): one round's BA (its
    report with "observations", None when there is nothing to adjust); a rig walk's holds the rig
    (:func:`stereoseed.sfm.rig.global_rig_adjust`)."""
    adjust_everything = adjust_everything or (lambda r, _: _adjust_everything(r, bundle, model))
    removed_per_round: list[int] = []
    rms_first = None
    while True:
        ba = adjust_everything(recon, len(removed_per_round))
        if ba is None:  # nothing registered past the pair: no BA, so nothing to judge by
            return ba_report(None), 0
        removed = drop_outliers(recon, outliers)
        removed_per_round.append(removed)
        rms_first = ba.get("rms_before_px") if rms_first is None else rms_first
        if (removed <= bundle.negligible_drop * ba["observations"]
                or len(removed_per_round) >= bundle.global_rounds):
            break
    ba.update(rounds=len(removed_per_round), removed_per_round=removed_per_round, rms_first_round_before_px=rms_first)
    return ba, sum(removed_per_round)


def _adjust_everything(recon: Reconstruction, bundle: BundleConfig, model: CameraModel) -> dict[str, Any] | None:
    """One BA of every registered view and point; on a subset of the points when the whole is
    large (see :func:`global_adjust`)."""
    views = recon.registered_views
    length = np.bincount(recon.obs_point[np.isin(recon.obs_view, views)], minlength=len(recon.points))
    if float(np.sum(length[recon.alive].astype(np.float64) ** 2)) <= bundle.subset_above:
        return adjust(recon, bundle, model, free_views=views)
    kept = select_tracks(recon, bundle.subset_cells)
    ba = adjust(recon, bundle, model, free_views=views, free_points=kept, points_in_cost=kept)
    if ba is None:
        return None
    others = np.setdiff1d(np.flatnonzero(recon.alive & (length > 0)), kept)
    points_ba = adjust(recon, bundle, model, free_views=[], free_points=others)  # cameras fixed: one 3x3 system a point
    # the report's RMS and eq. 14 are the camera adjustment's, on the subset's observations
    ba.update(subset_points=len(kept), other_points=len(others),
              other_points_rms_after_px=points_ba["rms_after_px"] if points_ba else None,
              seconds=ba["seconds"] + (points_ba["seconds"] if points_ba else 0.0),
              observations=ba["observations"] + (points_ba["observations"] if points_ba else 0))
    return ba


def select_tracks(recon: Reconstruction, cells: int) -> np.ndarray:
    """Ids (K,) of the live points a large global BA adjusts the cameras on: in each registered
    view's image, cut into ``cells`` x ``cells``, the point of the longest track it sees in each
    cell (the lowest reprojection error breaking ties). Every view keeps points spread over its
    image, and the long tracks, which tie many views together (the loop closure's links among
    them), are preferred: Theia's track subset selection for large bundle adjustments
    (Sweeney, Theia SfM; Kushal & Agarwal, "Visibility based preconditioning", CVPR 2012)."""
    rows = np.flatnonzero(recon.alive[recon.obs_point] & np.isin(recon.obs_view, recon.registered_views))
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    point, view = recon.obs_point[rows], recon.obs_view[rows]
    xy = recon.observation_xy(rows)
    size = np.array([v.image_size or (v.features.image_shape[1::-1] if v.features is not None else (1, 1))
                     for v in recon.views], np.float64)  # (V, 2) width, height
    col = np.clip(((xy[:, 0] + 0.5) * cells / size[view, 0]).astype(np.int64), 0, cells - 1)
    row = np.clip(((xy[:, 1] + 0.5) * cells / size[view, 1]).astype(np.int64), 0, cells - 1)
    cell = (view * cells + row) * cells + col
    length = np.bincount(point, minlength=len(recon.points))[point]
    error = recon.observation_errors()[rows]
    order = np.lexsort((error, -length, cell))
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    return unique(point[first])
