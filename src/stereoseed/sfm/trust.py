"""Whether each camera can be trusted, decided after the last insertion from everything the run
knows then (the field's answer to "a clean report on a wrong result"):

* its uncertainty: the 1-sigma position and rotation of the camera from the normal equations of
  the whole model (:func:`stereoseed.estimators.covariance.camera_uncertainty`, the calibrated
  pair as the gauge);
* its consistency: a camera whose observations reproject much worse than the other cameras'
  after the final BA is contradicted by them (a camera placed one period over on a repeated
  pattern keeps residuals the model cannot explain away), and so is a predicted camera that a
  camera found between its neighbours outdoes (:mod:`stereoseed.sfm.hindsight`; the caller gives
  those verdicts);
* its ties: a camera seeing too few points that other cameras also see is held where its
  registration put it, unchecked by the final BA; and a part of the walk tied to the calibrated
  pair only through a flagged camera floats once that camera leaves the model.

A camera that fails either is *flagged*: it stays registered (its P is written) but ``reliable``
is False with the reason, and, unless ``TrustConfig.keep_flagged``, its observations leave the
model, so no point and no dense match rests on it. :func:`judge` only returns the verdicts;
:mod:`stereoseed.sfm.finishing` applies them through the model.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereoseed.estimators.config import ResectionConfig
from stereoseed.geometry.camera_model import CameraModel
from stereoseed.sfm.config import MotionPriorConfig, TrustConfig
from stereoseed.estimators.covariance import CameraUncertainty, camera_uncertainty, point_regions
from stereoseed.geometry.projection import depths
from stereoseed.scene.camera_life import Flag, FlagKind, Status
from stereoseed.sfm.motion_prior import trusted_chain_inliers
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.rig import side_of, station_of, station_partner
from stereoseed.sfm.refinement import CALIBRATED, bundle_problem  # the pair: the frame itself, never flagged
from stereoseed.sfm.registration.base import FoundBy

__all__ = ["camera_uncertainties", "contradicted_cameras", "weakly_tied_cameras", "cut_off_cameras",
           "unconfirmed_cameras", "tied_observation_limit", "Verdicts", "judge"]



def camera_uncertainties(recon: Reconstruction, model: CameraModel, trust: TrustConfig) -> dict[int, CameraUncertainty]:
    """{view: its uncertainty} for every registered view after the pair, from the normal
    equations of all registered views (the pair fixed) and every live point, each camera's
    observations counted once per ``TrustConfig.independent_cell_px`` cell of its image, the
    larger of that and the residuals' own spread (``TrustConfig.spread_cell_px``); a rig
    walk's with one pose per station (the rig held, as its bundle adjustment holds it). model: the
    camera model the final BA used (the accurate mode holds the calibrated intrinsics when no
    image zoomed: the mode's ``adjustment_options``)."""
    built = bundle_problem(recon, model, recon.registered_views)
    if built is None:
        return {}
    problem, cams, _ = built
    regions = None if trust.spread_cell_px is None else point_regions(
        problem.obs_camera, problem.obs_point, problem.obs_xy, len(problem.points), trust.spread_cell_px)
    found = camera_uncertainty(problem, groups=None if recon.rig is None else _stations(recon, cams),
                               independent_cell_px=trust.independent_cell_px, point_clusters=regions)
    return {int(v): u for v, u in zip(cams, found) if u is not None}


def _stations(recon: Reconstruction, cams: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rig walk's cameras ``cams`` (C,) grouped by station for :func:`camera_uncertainty`: one
    pose per station, the left camera's; the right camera's rotation increment about its own
    axes is R_rl w and its translation's R_rl dt (R_r = R_rl R_l, t_r = R_rl t_l + t_rl), the
    rig's intrinsics held (the "fixed" model)."""
    R_rl = recon.rig.R_rl
    right = np.zeros((6, 6))
    right[:3, :3] = right[3:, 3:] = R_rl
    A = np.stack([right if side_of(int(v)) else np.eye(6) for v in cams])
    return np.array([station_of(int(v)) for v in cams]), A


def _median_depth(recon: Reconstruction, view: int) -> float:
    pts = recon.points[recon.points_seen_by(view)]
    return float(np.median(depths(recon.views[view].P, pts))) if len(pts) else float("nan")


def contradicted_cameras(recon: Reconstruction, trust: TrustConfig) -> dict[int, Flag]:
    """{view: flag} of the registered views after the pair whose observations reproject worse
    than ``TrustConfig.residual_factor`` x the median camera's RMS (and the floor)."""
    tc = trust
    views = [v for v in recon.registered_views if v not in CALIBRATED]
    live = recon.alive[recon.obs_point]
    if not views or not live.any():
        return {}
    err = recon.observation_errors()
    n_views = len(recon.views)
    seen = np.bincount(recon.obs_view[live], minlength=n_views)
    sq = np.bincount(recon.obs_view[live], weights=err[live] ** 2, minlength=n_views)
    observed = [v for v in recon.registered_views if seen[v]]
    if not observed:
        return {}
    rms = {v: float(np.sqrt(sq[v] / seen[v])) for v in observed}
    typical = float(np.median(list(rms.values())))
    limit = max(tc.residual_factor * typical, tc.residual_floor_px)
    observations = np.bincount(recon.obs_view, minlength=n_views)
    return {v: Flag(FlagKind.CONTRADICTED, f"its {int(observations[v])} observations "
                                           f"reproject at {rms[v]:.2f} px RMS, the cameras' median is {typical:.2f} px")
            for v in views if v in rms and rms[v] > limit}


def tied_observation_limit(trust: TrustConfig, motion_prior: MotionPriorConfig, resection: ResectionConfig) -> int:
    """Observations of multi-view points a camera needs for the final BA to check it."""
    if trust.min_tied_observations is not None:
        return trust.min_tied_observations
    return trusted_chain_inliers(motion_prior, resection)


def _tied(recon: Reconstruction, vouched: set[int]) -> np.ndarray:
    """(O,) bool: the observations by ``vouched`` views of live points that three of them see."""
    live = recon.alive[recon.obs_point] & np.isin(recon.obs_view, sorted(vouched))
    observers = np.bincount(recon.obs_point[live], minlength=len(recon.points))
    return live & (observers[recon.obs_point] >= 3)


def weakly_tied_cameras(recon: Reconstruction, need: int, vouched: set[int]) -> dict[int, Flag]:
    """{view: flag} of the registered views after the pair with fewer than
    ``need`` (:func:`tied_observation_limit`) observations of live points that two other cameras also see.
    A rig's station counts its two images' observations together (the rig holds them).
    vouched: the views the run vouches for: only their observations tie, and only they are
    judged (a flagged camera's observations leave the model; it vouches for nothing)."""
    tied = _tied(recon, vouched)
    group = station_of if recon.rig is not None else (lambda v: v)
    per_view = np.bincount(recon.obs_view[tied], minlength=len(recon.views))
    per_group: dict[int, int] = {}
    for v in recon.registered_views:
        per_group[group(v)] = per_group.get(group(v), 0) + int(per_view[v])
    return {v: Flag(FlagKind.WEAK, f"only {per_group[group(v)]} of its observations are of points two other cameras "
                                   f"also see; the final BA cannot check its place with fewer than {need}")
            for v in recon.registered_views
            if v not in CALIBRATED and v in vouched and per_group[group(v)] < need}


def cut_off_cameras(recon: Reconstruction, resection: ResectionConfig, vouched: set[int]) -> dict[int, Flag]:
    """{view: flag} of the ``vouched`` views after the pair that no chain of vouched views links
    to the calibrated pair with at least ``ResectionConfig.min_inliers`` shared points (points
    three vouched cameras see, which carry the pair's frame and scale from camera to camera) at
    every link: a part of the walk joined to the rest only through a flagged camera floats once
    that camera's observations leave the model (dinoSparseRing walked back from its 12th image:
    four cameras after a flagged one, 15-34 mm off, each well tied to the others of its part). A
    rig's station is one body: its two images are linked."""
    need = resection.min_inliers
    shared = recon.shared_points(_tied(recon, vouched))
    reached, frontier = set(CALIBRATED), list(CALIBRATED)
    while frontier:
        u = frontier.pop()
        row = shared.getrow(u)
        linked = [int(w) for w in row.indices[row.data >= need]]
        if recon.rig is not None:
            linked.append(station_partner(u))
        for w in linked:
            if w in vouched and w not in reached:
                reached.add(w)
                frontier.append(w)
    tied_to_pair = sorted(reached)
    return {v: Flag(FlagKind.WEAK, f"no chain of the cameras the run vouches for ties it to the calibrated pair: it "
                                   f"shares at most {int(shared[v, tied_to_pair].max())} points seen by three of them "
                                   f"with those tied to the pair (a link needs {need})")
            for v in sorted(vouched) if v not in reached}


def unconfirmed_cameras(recon: Reconstruction, resection: ResectionConfig, vouched: set[int],
                        motion_prior: MotionPriorConfig) -> dict[int, Flag]:
    """{view: flag} of the ``vouched`` views that no later vouched camera confirms: none shares
    ``ResectionConfig.min_inliers`` live points with it that a third vouched camera also sees (a
    later camera placed from it observes its points again). Judged so: the views placed on the
    weakest evidence (the motion prior's prediction, or the propagated matches alone), and any
    view after which the run tried an image and failed (the walk could not go on from it). The
    calibrated pair confirms a view only when it was not among the registered views it was placed
    from (``MotionPriorConfig.recent_views``): the end of a walk its loop closure tied to the
    start. A prediction nothing after it checks is the walk's last word on it (docs/mapper.md, "A
    prediction nothing later confirms", has the cameras each rule caught)."""
    need = resection.min_inliers
    # only points a third vouched camera also sees: the points v and w triangulated together
    # fit both whatever v's error along their baseline (a 24-megapixel walk's img_027 stood 7 %
    # of its distance off, "confirmed" by the next camera through such points)
    shared = recon.shared_points(_tied(recon, vouched))
    last_failed = max((u for u, view in enumerate(recon.views) if view.life.status == Status.FAILED), default=-1)
    out = {}
    for v in sorted(vouched - set(CALIBRATED)):
        found_by = recon.views[v].found_by
        weakest = found_by in (FoundBy.MOTION_PRIOR, FoundBy.QUASI_DENSE)
        if not weakest and v > last_failed:
            continue
        placed_from = set(recon.registered_before(v, motion_prior.recent_views))
        confirming = [w for w in vouched if w > v or (w in CALIBRATED and w not in placed_from)]
        best = max((int(shared[v, w]) for w in confirming), default=0)
        if best < need:
            how = f"placed by the {found_by} alone" if weakest else "the images after it could not be placed"
            out[v] = Flag(FlagKind.WEAK, f"{how}, and no later camera confirms it (the one sharing most of its "
                                         f"points that a third camera sees shares {best}; a confirmation needs {need})")
    return out


def _uncertain(recon: Reconstruction, view: int, u: CameraUncertainty, trust: TrustConfig) -> Flag | None:
    if not u.determined:
        return Flag(FlagKind.UNCERTAIN, u.reason)
    depth = _median_depth(recon, view)
    worst = float(np.max(u.position_sigma))
    if np.isfinite(depth) and worst > trust.max_position_sigma * depth:
        return Flag(FlagKind.UNCERTAIN, f"3-sigma position {3 * worst:.3g} ({300 * worst / depth:.1f} % of its distance "
                                        f"to the scene, limit {300 * trust.max_position_sigma:.1f} %)")
    return None


def _flag_stations(recon: Reconstruction, flags: dict[int, Flag | None]) -> None:
    """A rig's station is one rigid body: what places one of its images wrongly places both."""
    if recon.rig is None:
        return
    for v in recon.registered_views:
        partner = station_partner(v)
        if flags[v] is None and flags.get(partner):
            flags[v] = flags[partner].through(recon.views[partner].name)


@dataclass(frozen=True)
class Verdicts:
    """The judgement of every registered camera: its flag (None: the run vouches for it) and its
    uncertainty (the views after the pair whose normal equations give one)."""

    flags: dict[int, Flag | None]
    uncertainties: dict[int, CameraUncertainty]


def judge(recon: Reconstruction, between_neighbours: dict[int, Flag], *, trust: TrustConfig,
          resection: ResectionConfig, motion_prior: MotionPriorConfig, model: CameraModel) -> Verdicts:
    """Judge every registered camera (the module's rules); changes nothing. A flag raised while
    the camera was placed (an ambiguous choice) stays; else its residuals, the verdicts of its
    neighbours (``between_neighbours``: :func:`stereoseed.sfm.hindsight.contradicted_by_neighbours`
    on this very model, or {}), its uncertainty (under ``model``: :func:`camera_uncertainties`)
    and its ties decide."""
    contradicted = contradicted_cameras(recon, trust)
    contradicted.update(between_neighbours)
    uncertainties = camera_uncertainties(recon, model, trust)
    flags: dict[int, Flag | None] = {}
    for v in recon.registered_views:
        u = uncertainties.get(v)
        flags[v] = None if v in CALIBRATED else (recon.views[v].placement_flag or contradicted.get(v)
                                                 or (None if u is None else _uncertain(recon, v, u, trust)))
    if recon.rig is None:  # (a rig's stations are placed by the rig, from both their images)
        # judged among the cameras vouched for so far: one unconfirmed prediction does not
        # unconfirm the one before it, which it observed again
        unconfirmed = unconfirmed_cameras(recon, resection, {v for v, flag in flags.items() if flag is None},
                                          motion_prior)
        flags.update(unconfirmed)
    _flag_stations(recon, flags)
    # ties to flagged cameras hold nothing: each flag may leave another camera weakly tied
    # (a station's two images are judged together: both or neither)
    # (and a flag may cut a part of the walk off the pair)
    need = tied_observation_limit(trust, motion_prior, resection)
    while weak := (weakly_tied_cameras(recon, need, vouched := {v for v, flag in flags.items() if flag is None})
                   or cut_off_cameras(recon, resection, vouched)):
        flags.update(weak)
    return Verdicts(flags, uncertainties)
