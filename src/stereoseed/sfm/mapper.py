"""The incremental mapper (paper §4.1-4.3): estimate, validate, then commit.

    recon, report = initialise(images, names, P_pair, options, source)   # match I1-I2, triangulate
    for k in 2 .. n-1: insert_view(recon, k, options, source)           # register, grow, adjust
    finish(recon, options, source)                                      # loop closure, final BA, hindsight, trust

``options``: the :class:`~stereoseed.sfm.options.MapperOptions` built once at the top
(:meth:`stereoseed.config.Config.mapper_options`; a plain ``Config`` is taken too and gives its
own); the mapper hands each component its own sections.

The reconstruction is data; ``source`` (a :class:`~stereoseed.sfm.correspondence.CorrespondenceSource`,
default :class:`~stereoseed.sfm.correspondence.HarrisZncc`) is where its correspondences come from.

:func:`insert_view` registers view k through the registrars in the order
:func:`stereoseed.sfm.strategy.registrars` gives (each
changes nothing) and commits the camera at one point only; then the mode's strategy
(:mod:`stereoseed.sfm.modes`) adds points, grows tracks and adjusts. An image that cannot be
placed is reported (``"status": "failed"`` with the reason) and leaves the reconstruction as it
was; so does a numerical failure after the commit (the insertion is rolled back). One that cannot
be placed after a view flagged at its registration is tried again without that view; placed so,
it withdraws it (its report's "withdrawn"): a successful insertion may take an earlier view out.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import numpy as np

from stereoseed.geometry.projection import epipolar_distances, fundamental_from_projections
from stereoseed.sfm.correspondence import CorrespondenceSource, HarrisZncc, optional
from stereoseed.errors import StereoseedError
from stereoseed.matching.containers import Matches
from stereoseed.scene.camera_life import Flag, FlagKind, report_of
from stereoseed.sfm.config import PairCheckConfig
from stereoseed.estimators.config import BundleConfig
from stereoseed.matching.config import MatchingConfig
from stereoseed.sfm.modes import Mode, holds_intrinsics
from stereoseed.sfm.options import Configuration, MapperOptions, options_of
from stereoseed.sfm.strategy import mode_of, registrars
from stereoseed.sfm.finishing import finish
from stereoseed.scene.reconstruction import Reconstruction, View
from stereoseed.sfm.registration.quasi_dense import grow_quasi_dense
from stereoseed.sfm.refinement import adjust, ba_report, drop_outliers
from stereoseed.sfm.registration.base import (FailureKind, FoundBy, Registration, RegistrationFailure,
                                              consistent_chain, reported_notes)
from stereoseed.scene.view_store import view_of_input
from stereoseed.sfm.tracks import add_two_view_points, new_points_three_view
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.camera import Camera
from stereoseed.estimators.robust import huber_cost_of_norms
from stereoseed.estimators.rig_resection import Rig

__all__ = ["initialise", "insert_view", "finish", "pair_rig"]

log = logging.getLogger(__name__)


def _refine(recon: Reconstruction, source: CorrespondenceSource, a: int, b: int, m: Matches) -> None:
    """Move view b's matched interest points onto their partners in view a, if the source can."""
    refine = optional(source, "refine")
    if refine is not None and len(m):
        recon.views[b].features = refine(recon.views[a].features, recon.views[b].features, m)


def _match_known(recon: Reconstruction, source: CorrespondenceSource, a: int, b: int) -> Matches:
    """Matches between registered views a and b under their epipolar geometry."""
    va, vb = recon.views[a], recon.views[b]
    return source.match(a, b, va.features, vb.features, fundamental_from_projections(va.P, vb.P),
                        va.image_size[0])


def pair_rig(P_pair: list[np.ndarray], rig: bool) -> Rig | None:
    """The rig a walk with both cameras holds (its first station, the calibrated pair), else None."""
    return Rig.from_projections(*P_pair[:2]) if rig else None


def initialise(images: list[np.ndarray], names: list[str], P_pair: list[np.ndarray],
               options: MapperOptions | Configuration, source: CorrespondenceSource | None = None,
               rig: bool = False) -> tuple[Reconstruction, dict[str, Any]]:
    """Paper §4.1: the calibrated pair. Harris + ZNCC matches under the known epipolar geometry,
    linear + LM triangulation, filtered by reprojection error, cheirality and angle.

    images: the sequence (uint8 BGR); P_pair: the pair's two (3, 4) cameras; source: where
    correspondences come from (default :class:`HarrisZncc`; give the same one to every later
    step). rig: the images are a stereo rig's stations (left, right, left, ...; the pair is the
    first station, :mod:`stereoseed.sfm.rig`). options: the mapper's (module docstring).
    Raises :class:`StereoseedError` when the pair
    gives too few points (the calibration does not belong to these images)."""
    t0 = time.perf_counter()
    options = options_of(options)
    recon = Reconstruction([view_of_input(n, images, i) for i, n in enumerate(names)], pair_rig(P_pair, rig))
    source = source or HarrisZncc.of(options)
    for i in (0, 1):
        view = recon.views[i]
        recon.calibrate(i, P_pair[i])
        view.features = source.features(i, view.image)
        view.point_of_feature = np.full(len(view.features), -1, np.int64)
        if len(view.features) == 0:
            h, w = view.image.shape[:2]
            border = options.features.border
            why = (f"the features' border of {border} px leaves nothing of a {w}x{h} image; lower [features] border"
                   if 2 * border >= min(w, h) else "a blank or black image?")
            raise StereoseedError(f"{names[i]}: no interest points ({why}); the calibrated pair must show the object")
    _check_pair(recon, source, options.pair_check, options.matching)
    m = _match_known(recon, source, 0, 1)
    _refine(recon, source, 0, 1, m)
    ids = add_two_view_points(recon, 0, 1, m, options.triangulation, colour_view=0)
    if len(ids) < options.resection.min_inliers:  # a fresh model: nothing to undo but the model itself
        raise StereoseedError(f"{names[0]}, {names[1]}: only {len(ids)} points triangulated from the calibrated pair "
                              f"({len(m)} matches); check the calibration belongs to these two images")
    report = {"image": names[1], "status": "calibrated pair", "matches": len(m), "new_points": len(ids),
              "seconds": {"total": time.perf_counter() - t0}}
    recon.record(0, {"image": names[0], "status": "calibrated"})
    recon.record(1, report)
    return recon, report


def _check_pair(recon: Reconstruction, source: CorrespondenceSource, pair_check: PairCheckConfig,
                matching: MatchingConfig) -> None:
    """The calibration must fit its two images: their matches found without it (robust F) must
    lie on its epipolar lines (``PairCheckConfig.min_consistent``), or, when they do not,
    matching under the calibration's epipolar geometry must find at least
    ``PairCheckConfig.min_known_ratio`` times as many. Raises
    :class:`StereoseedError` naming the likely causes."""
    v0, v1 = recon.views[0], recon.views[1]
    if v0.image.shape == v1.image.shape and np.array_equal(v0.image, v1.image):
        raise StereoseedError(f"{v0.name}, {v1.name}: the calibrated pair is the same image twice; give the two "
                              f"images the two calibrated cameras took")
    m = source.match(0, 1, v0.features, v1.features, None, v0.image.shape[1])
    if len(m) < pair_check.min_matches:
        return  # repeated patterns or little texture: no robust F to judge by
    x0, x1 = m.points(v0.features, v1.features)
    d = epipolar_distances(fundamental_from_projections(v0.P, v1.P), x0, x1)
    consistent = float(np.mean(d <= matching.epipolar_band_px))
    if (consistent < pair_check.min_consistent
            and len(_match_known(recon, source, 0, 1)) < pair_check.min_known_ratio * len(m)):
        # A robust F can also lock onto a wrong period of a repeated pattern (a box of squares);
        # then the calibration's own epipolar geometry still matches about as many as that F does,
        # while a calibration of other images matches only what falls in its bands by chance.
        raise StereoseedError(
            f"{v0.name}, {v1.name}: the calibration does not fit these images: only {100 * consistent:.0f} % of "
            f"their {len(m)} matches lie on its epipolar lines (a fitting one: ~100 %); are the two cameras "
            f"swapped, the images in the wrong order, or the calibration another pair's? (Or do the two "
            f"images show little but a repeated pattern, matched one period over? Then photograph the pair "
            f"with more of the scene in view.)")


def insert_view(recon: Reconstruction, k: int, options: MapperOptions | Configuration,
                source: CorrespondenceSource | None = None) -> dict[str, Any]:
    """Paper §4.2-4.3: register view k from the last registered view, add its points, adjust.
    source: the correspondences :func:`initialise` was given (default :class:`HarrisZncc`);
    options: the mapper's (module docstring).

    Returns a JSON-able report (also the view's, in its history): "status" is "registered" or
    "failed" (with "reason"); a failed view leaves ``recon`` as it was (only the view's history
    records why). "withdrawn" ({name: reason}, when present): k was placed only once the view
    before it, doubted when placed (:func:`_doubted_when_placed`), was taken out of the model
    (:func:`_without_doubted_previous`; that view's history says so)."""
    options = options_of(options)
    source = source or HarrisZncc.of(options)
    view = recon.views[k]
    found = _registered(recon, source, k, options)
    withdrawn = {}
    if isinstance(found, RegistrationFailure):
        retried = _without_doubted_previous(recon, source, k, found, options)
        if isinstance(retried, RegistrationFailure):
            return _failed(recon, k, retried.reason, retried)
        found, withdrawn, state, state_without = retried
    else:
        state = state_without = recon.checkpoint()  # the model before this insertion
    try:
        report = _commit_and_grow(recon, source, k, found, options)
    except np.linalg.LinAlgError as e:
        recon.restore(state)
        why = f"; placed only without {', '.join(withdrawn)}, which stays" if withdrawn else ""
        return _failed(recon, k, f"{view.name}: numerical failure ({e}){why}; skipped", found)
    except BaseException:  # anything else (a bug, an interrupt) propagates, with the model as it was
        recon.restore(state)
        raise
    # the model before this insertion, while the view is doubted: what its withdrawal restores
    recon.insertion_undo = (k, state_without) if _doubted_when_placed(view) else None
    for reason in withdrawn.values():
        log.info("%s", reason)
    if withdrawn:
        report["withdrawn"] = withdrawn
    recon.record(k, report)
    return report


# the failures an image may owe to the view it was chained to (not its size, not roundoff)
_CHAIN_FAILURES = (FailureKind.TOO_FEW_MATCHES, FailureKind.NO_CAMERA, FailureKind.DISAGREES)


def _registered(recon: Reconstruction, source: CorrespondenceSource, k: int,
                options: MapperOptions) -> Registration | RegistrationFailure:
    """View k's camera from the registrars (:func:`stereoseed.sfm.strategy.registrars`), the
    model unchanged."""
    found = None
    settings = options.registering
    for registrar in registrars(recon):
        found = registrar.register(recon, source, k, found, settings)
    return found


def _doubted_when_placed(view: View) -> str | None:
    """Why ``view``'s registration is weak evidence for its camera, or None: flagged when placed
    (a choice between copies of a repeated pattern, a zoom it could not measure), or placed by
    the propagated matches alone (the sparse chain was too weak to place it)."""
    if view.placement_flag:
        return f"flagged when placed ({view.placement_flag})"
    return "placed by the propagated matches alone" if view.found_by == FoundBy.QUASI_DENSE else None


def _without_doubted_previous(recon: Reconstruction, source: CorrespondenceSource, k: int, failure: RegistrationFailure,
                              options: MapperOptions
                              ) -> tuple[Registration, dict[str, str], Any, Any] | RegistrationFailure:
    """View k could not be placed after a view whose registration is weak evidence
    (:func:`_doubted_when_placed`: flagged at its registration, or placed by the propagated
    matches alone): that failure is evidence against that camera, whose points are what k was
    chained to (the castle from 0008: 0013, placed by propagated matches 0.35 m off, left every
    later image unplaced). k is tried again with that view withdrawn, after the view before it.
    The withdrawal puts the model back as it was before the doubted view's insertion (its points,
    the adjustments and outlier removals it caused), where the run kept that state (not after a
    resume: then only its camera and observations leave). When k is placed so, the doubted view
    stays out: returns (k's registration, {withdrawn view's name: reason}, the model as it was, the
    model without it: checkpoints); otherwise the model is put back and the failure returned, with
    what the second try said. A walk that went on from a wrong copy of a pattern (the castle walked
    backwards: 2.2 m off, flagged) otherwise lost every later image. Not for a rig walk, whose
    stations are judged as one body (:mod:`stereoseed.sfm.rig`)."""
    before = recon.registered_before(k, 1)
    if recon.rig is not None or failure.kind not in _CHAIN_FAILURES or not before or before[0] < 2:
        return failure  # (views 0 and 1: the calibrated pair, never withdrawn)
    p = before[0]
    view = recon.views[p]
    doubt = _doubted_when_placed(view)
    if not doubt:
        return failure
    state = recon.checkpoint()
    kept = recon.insertion_undo
    reason = (f"{view.name}: withdrawn: {doubt}, and the next image, {recon.views[k].name}, "
              f"was placed only without it")
    # tried without p: the model as before p's insertion where the run kept it
    recon.withdraw(p, reason, kept[1] if kept is not None and kept[0] == p else None)
    found = _registered(recon, source, k, options)
    if isinstance(found, RegistrationFailure):
        recon.restore(state)
        return dataclasses.replace(failure, notes={**failure.notes, "without_flagged_previous": found.reason})
    recon.insertion_undo = None
    return found, {view.name: reason}, state, recon.checkpoint()


def _failed(recon: Reconstruction, k: int, reason: str, found: Registration | RegistrationFailure) -> dict[str, Any]:
    """View k could not be placed (``reason``): recorded in its history; its report."""
    log.info("%s", reason)
    failure = found.kind if isinstance(found, RegistrationFailure) else FailureKind.NUMERICAL
    report = {"image": recon.views[k].name, "status": "failed", "reason": reason, "failure": failure,
              "matches": found.matches, "chained_points": found.chained_points, **reported_notes(found),
              "seconds": dict(found.seconds, total=float(sum(found.seconds.values())))}
    recon.fail(k, reason, report)
    return report


def _commit(recon: Reconstruction, k: int, reg: Registration) -> None:
    """The one place where a registered camera enters the reconstruction."""
    cand = reg.candidate
    recon.register(k, reg.resection.camera, reg.found_by, cand.features, cand.image, cand.rotated_180,
                   CameraModel.FOCAL if reg.free_camera_refused else None, reg.zoomed, reg.flag)


def _commit_and_grow(recon: Reconstruction, source: CorrespondenceSource, k: int, reg: Registration,
                     options: MapperOptions) -> dict[str, Any]:
    """Commit view k's camera, then: re-match under the now-known epipolar geometry, extend the
    chained tracks, triangulate the new points, grow the tracks, adjust, drop outliers."""
    mode = mode_of(options.pipeline, recon)
    view = recon.views[k]
    prev = recon.registered_before(k, 1)[0]
    _commit(recon, k, reg)
    report: dict[str, Any] = {"image": view.name, "matches": reg.matches, "chained_points": reg.chained_points,
                              "registered_by": reg.found_by, **reported_notes(reg)}
    if reg.quasi_dense is not None:
        report["quasi_dense"] = reg.quasi_dense.report
    if view.rotated_180:
        report["rotated_180"] = True
    if reg.hypothesis is not None:
        report["motion_prior_correspondences"] = len(reg.hypothesis)
        report["motion_prior_search"] = {"radius_fraction": reg.hypothesis.radius_fraction,
                                         "pairings_per_point": reg.hypothesis.pairings_per_point}
    report.update(resection_inliers=int(reg.resection.inliers.sum()), resection_rms_px=reg.resection.rms_px,
                  resection_model=reg.model)
    if reg.free_camera_refused:
        report["free_camera_refused"] = reg.free_camera_refused
    timing = dict(reg.seconds)

    t = time.perf_counter()
    m = _match_known(recon, source, prev, k)
    _refine(recon, source, prev, k, m)
    # the chained observations consistent with the camera just estimated
    pid, chained, consistent = consistent_chain(recon, prev, k, m, options.resection.ransac_threshold_px)
    chain_points = pid[consistent]
    ids = mode.add_points(recon, prev, k, m, chained, consistent, chain_points, options.triangulation)
    if reg.quasi_dense is not None and options.quasi_dense.keep_tracks:  # the propagated matches' tracks
        more, more_chained, report["quasi_dense_tracks"] = grow_quasi_dense(recon, prev, k, reg, mode,
                                                                            options.quasi_dense, options.resection,
                                                                            options.triangulation)
        ids, chain_points = np.concatenate([ids, more]), np.concatenate([chain_points, more_chained])
    if reg.found_by == FoundBy.MOTION_PRIOR:
        # repeated patterns defeated two-view matching: let a third view decide
        before = recon.registered_before(prev, 1)
        if before:
            more = new_points_three_view(recon, prev, k, before[0], options.tracking, options.matching,
                                         options.triangulation)
            ids = np.concatenate([ids, more])
            report["three_view_points"] = int(len(more))
    expect_match = optional(source, "expect_match")
    partner = mode.next_match(k)

    def features_final() -> None:  # k's interest points are final: the next insertion's matching may start
        if expect_match is not None and partner is not None:
            expect_match(k, view.features, view.image_size[0], partner)

    report.update(mode.grow_tracks(recon, source, k, chain_points, options, features_final))
    timing["triangulation"] = time.perf_counter() - t
    report.update(matches_guided=len(m), chained_observations=int(len(chain_points)), new_points=int(len(ids)))

    t = time.perf_counter()
    ba_options = mode.adjustment_options(recon, options)
    if ba_options is not options:
        report["ba_intrinsics"] = "calibrated (no zoom found yet)"
    if options.pipeline.ba == "global":
        ba = ba_report(adjust(recon, ba_options.bundle, ba_options.pipeline.camera_model,
                              free_views=recon.registered_views))
    elif _lens_in_question(recon, k, options):
        ba, report["zoom_evidence"] = _lens_judged_by_the_window(recon, mode, prev, k, ids, chain_points, options)
        if not view.zoomed:
            report["ba_intrinsics"] = "calibrated (the window's BA did not take the resection's zoom)"
    else:
        ba = mode.local_adjust(recon, prev, k, ids, chain_points, ba_options)
    timing["bundle"] = time.perf_counter() - t
    removed = drop_outliers(recon, options.outliers)
    report.update(ba=ba, removed_observations=removed, seconds=timing, status="registered")
    report["seconds"]["total"] = float(sum(timing.values()))
    return report


def _lens_in_question(recon: Reconstruction, k: int, options: MapperOptions) -> bool:
    """Whether view k is the first whose resection took a zoom while the run holds the calibrated
    intrinsics (the "focal" model with ``hold_unzoomed``): the window's BA judges it
    (:func:`_lens_judged_by_the_window`)."""
    return recon.views[k].zoomed and holds_intrinsics(recon, options.pipeline, besides=k)


def _weakly_placed(recon: Reconstruction, v: int) -> bool:
    """Whether view v's camera rests on weak evidence: a sparse registration the run judged weak
    (its report's ``sparse_weak``: below the trusted chain, or the motion prior's camera
    predicted across a gap) and kept because the quasi-dense matches did not place it."""
    report = report_of(recon.views[v].history) or {}
    return "sparse_weak" in report and report.get("registered_by") in (FoundBy.MOTION_PRIOR, FoundBy.EPIPOLAR_CHAIN)


def _lens_judged_by_the_window(recon: Reconstruction, mode: Mode, prev: int, k: int, ids: np.ndarray,
                               chain_points: np.ndarray, options: MapperOptions
                               ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Whether view k's resection found the walk's first zoom, or the calibrated lens setting
    holds: the window's BA under each (k's focal length free, or held), compared by BIC over the
    window's observations (one parameter more) with the resections' margin
    ``ResectionConfig.zoom_evidence_bic``, on the Huber cost the BA minimises (an outlier's square
    would pass for evidence). A resection judges a zoom on its 3D points as if they were exact;
    here the points move with the cameras. Each hypothesis starts from the resection's pose, the
    held one's centre moved along the ray through the points' centroid so that the points keep
    their image size. A zoom is taken only where the window measures it
    (``RegistrationConfig.max_focal_sigma``, ``zoom_certain_sigmas``); one it asks for but cannot
    measure is not, and the view is flagged uncertain. The model is left with the BA chosen
    (``view.zoomed`` says which). -> (that BA's report, the evidence)."""
    view = recon.views[k]
    window = recon.registered_views[-options.pipeline.window:]
    sel = np.isin(recon.obs_view, window)
    start = recon.checkpoint()
    seen = recon.points[recon.points_seen_by(k)]
    held = options.held()
    runs = {}
    for zoomed in (False, True):
        recon.restore(start)
        view.zoomed = zoomed
        if not zoomed:  # the calibrated focal length, the points at the same image size
            view.camera = _refocused(view.camera, recon.reference_K(k)[0, 0], seen)
        ba = mode.local_adjust(recon, prev, k, ids, chain_points, options if zoomed else held)
        runs[zoomed] = (ba, _window_cost(recon, sel, options.bundle), recon.checkpoint(), view.camera.focal)
    n = 2 * int(np.sum(sel & recon.alive[recon.obs_point]))
    (_, cost_same, _, f_same), (_, cost_new, _, f_new) = runs[False], runs[True]
    # the likelihood-ratio statistic, about (zoom / its 1-sigma)^2 (Wilks): the profile of the
    # cost along the focal length gives the sigma without inverting the normal equations
    ratio = n * np.log(cost_same / cost_new) if n and cost_new > 0 else np.inf
    evidence = ratio - np.log(n) if n else -np.inf
    zoom = abs(f_new / f_same - 1.0)
    sigma = zoom / np.sqrt(ratio) if ratio > 0 else np.inf
    asked = bool(evidence > options.resection.zoom_evidence_bic)
    rc = options.registration
    measured = sigma <= rc.max_focal_sigma or zoom >= rc.zoom_certain_sigmas * sigma
    # A camera chosen on a margin (a repeated pattern) does not decide the lens of the whole walk,
    # nor does a window that holds a weakly placed camera: a zoom explains its offset as well as
    # the offset itself does (strechaCastleP19 under OpenCV 4.10: 0014 kept on 13 inliers, 0015
    # then took a 4 % zoom that put it 1.26 % off at a stated 0.08 %; docs/benchmarks.md)
    weak = [recon.views[v].name for v in window if v != k and _weakly_placed(recon, v)]
    kept = bool(asked and measured and not view.placement_flag and not weak)
    recon.restore(runs[kept][2])
    view.zoomed = kept
    out = {"bic_for_the_zoom": float(evidence), "zoom": float(zoom), "focal_sigma": float(sigma), "kept": kept}
    if asked and measured and weak:
        out["weakly_placed_in_window"] = weak
    if asked and not measured:
        flag = Flag(FlagKind.UNCERTAIN, f"its residuals ask for a {100 * zoom:.1f} % zoom that this view measures only "
                                        f"to {100 * sigma:.1f} % (1 sigma; a zoom and a step along the optical axis "
                                        f"look alike here)")
        recon.flag(k, flag)
        out["flag"] = flag.reason
    return runs[kept][0], out


def _refocused(camera: Camera, focal: float, points: np.ndarray) -> Camera:
    """``camera`` with focal length ``focal`` (px; the principal point and aspect kept) and its
    centre moved along the ray to the centroid of ``points`` (N, 3) by the focal lengths' ratio:
    the points keep their image size (a zoom and a step back look alike)."""
    K = camera.K.copy()
    ratio = focal / camera.focal
    K[:2, :2] *= ratio
    C = camera.centre
    if len(points):
        target = points.mean(axis=0)
        C = target + (C - target) * ratio
    return Camera.from_krt(K, camera.R, -camera.R @ C, camera.model, camera.lens)


def _window_cost(recon: Reconstruction, sel: np.ndarray, bundle: BundleConfig) -> float:
    err = recon.observation_errors(sel & recon.alive[recon.obs_point])
    return 2.0 * huber_cost_of_norms(err[np.isfinite(err)], bundle.huber_px)
