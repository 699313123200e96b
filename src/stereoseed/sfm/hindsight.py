"""A camera judged again once the walk has placed its neighbours (issue "Cameras you can trust",
consistency after the fact).

At its registration a camera was predicted from the motion before it (extrapolated); once the
views on both sides are placed, the camera between them is predicted far better (interpolated).
The motion prior's search around that prediction (:func:`stereoseed.sfm.motion_prior.hypotheses_near`)
gives cameras that compete with the one the run kept by the neighbours' points they explain
(:func:`stereoseed.sfm.motion_prior.explained_points`), as at registration. A rival standing
apart (``TrustConfig.ambiguity_shift`` of the depth) that explains clearly more
(``MotionPriorConfig.wider_search_margin`` times the points) contradicts the camera: on the
castle walked from its 11th image, 0016 was placed 3.7 m off on the wrong copy of the windows
(it explains 150 of its neighbours' points; a camera 3.7 m away, the true one, 275). Rivals
that explain nearly as much are no evidence here: a good camera has them too (2-5 % of the
depth away, on the castle and the dino).

Such a rival, unless it is a choice on a margin itself, then takes the camera's place
(:func:`register_again`): the camera's observations go, the neighbours' points the rival
explains become its observations, and the camera is refined on them; else the camera is
flagged. The cameras flagged at their registration are tried too (the castle's 0008 and 0016,
chosen on a margin between copies of the windows): the neighbours on both sides are evidence
their registration did not have.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from stereoseed.geometry.projection import camera_center, depths
from stereoseed.scene.camera_life import Flag, FlagKind
from stereoseed.sfm.modes import adjust_globally
from stereoseed.sfm.options import MapperOptions
from stereoseed.sfm.strategy import mode_of
from stereoseed.sfm.motion_prior import described_points, explained_points, explaining_matches, hypotheses_near
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.refinement import CALIBRATED, adjust
from stereoseed.sfm.registration.base import Candidate, FoundBy, Resector, ambiguous_rivals, ambiguity_flag
from stereoseed.sfm.registration.settings import RegistrationSettings

__all__ = ["contradicted_by_neighbours", "register_again", "Hindsight", "between", "Rival"]

log = logging.getLogger(__name__)


def between(P_a: np.ndarray, P_b: np.ndarray, K: np.ndarray, t: float) -> np.ndarray:
    """The camera (3, 4) with intrinsics K (3, 3) a fraction ``t`` of the way from camera P_a to
    camera P_b (3, 4): its centre on the segment, its rotation on the shortest arc."""
    poses = []
    for P in (P_a, P_b):
        R = np.linalg.solve(K, P[:, :3])
        U, _, Vt = np.linalg.svd(R)  # the nearest rotation (P_a, P_b may carry other intrinsics)
        poses.append((U @ Vt * np.sign(np.linalg.det(U @ Vt)), camera_center(P)))
    R = Slerp([0.0, 1.0], Rotation.from_matrix([poses[0][0], poses[1][0]]))([t]).as_matrix()[0]
    C = (1.0 - t) * poses[0][1] + t * poses[1][1]
    return K @ np.hstack([R, -(R @ C)[:, None]])


@dataclass(frozen=True)
class Rival:
    """A camera for a view found between its neighbours ``a`` and ``b`` that explains
    ``explains`` of their points (``points`` (K,) ids, described by ``desc`` (K, D)), clearly more
    than the ``kept`` the run's camera explains; P (3, 4) stands ``distance`` from the run's
    camera, whose median depth is ``depth``. ``margin``: why the rival itself is ambiguous (a
    camera found there, the run's included, stands a period away and explains nearly as much:
    :func:`stereoseed.sfm.registration.base.ambiguity_flag`), or None."""

    a: int
    b: int
    P: np.ndarray
    explains: int
    kept: int
    distance: float
    depth: float
    points: np.ndarray
    desc: np.ndarray
    margin: Flag | None

    def where(self, recon: Reconstruction) -> str:
        return (f"a camera {self.distance:.3g} away ({100 * self.distance / self.depth:.1f} % of the scene's depth), "
                f"found between {recon.views[self.a].name} and {recon.views[self.b].name}, explains {self.explains} "
                f"of their points, this one {self.kept}")

    def contradiction(self, recon: Reconstruction) -> Flag:
        """The flag it puts on the view's camera."""
        return Flag(FlagKind.CONTRADICTED, self.where(recon))


def _rival(recon: Reconstruction, settings: RegistrationSettings, k: int, a: int, b: int) -> Rival | None:
    """The rival of view k's camera between views a < k < b (the module's rule), or None."""
    mp, tc = settings.motion_prior, settings.trust
    view = recon.views[k]
    # their points, each described by its patch at its first observation in a or b
    pids, desc = described_points(recon, np.flatnonzero(np.isin(recon.obs_view, [a, b])
                                                         & recon.alive[recon.obs_point]), a)
    if len(pids) < settings.resection.min_points:
        return None
    # the resection reads only the image's size: no pixels read again
    size_only = np.broadcast_to(np.zeros((), np.uint8), view.image_size[::-1])
    cand = Candidate(k, view.name, size_only, view.features, view.rotated_180)
    resect = Resector(recon, a, cand, settings)
    cameras = [view.P]
    for hypotheses in hypotheses_near(recon, between(recon.views[a].P, recon.views[b].P, view.K, (k - a) / (b - a)),
                                      view.features, mp, settings.resection, (pids, desc)):
        cameras += [res.P for (res, _), _ in resect.each(hypotheses)[0]]
    counts = explained_points(view.features, cameras, recon.points[pids], desc, mp.explain_px, mp.min_zncc)
    depth = float(np.median(depths(view.P, recon.points[pids])))
    centre = camera_center(view.P)
    rivals = [(int(n), float(np.linalg.norm(camera_center(P) - centre)), i)
              for i, (n, P) in enumerate(zip(counts[1:], cameras[1:]), start=1)]
    # clearly more, and at least a resection's worth (a count of 0 against 0 says nothing)
    rivals = [(n, d, i) for n, d, i in rivals
              if n >= max(mp.wider_search_margin * counts[0], settings.resection.min_inliers)
              and d > tc.ambiguity_shift * depth]
    if not rivals:
        return None
    n, d, i = max(rivals)
    margin = ambiguity_flag(ambiguous_rivals(recon, a, pids, cameras, counts, i, tc), counts, i)
    return Rival(a, b, cameras[i], n, int(counts[0]), d, depth, pids, desc, margin)


def _rivals_between(recon: Reconstruction, settings: RegistrationSettings, sound: list[int],
                    views: list[int]) -> Iterator[tuple[int, Rival]]:
    """(k, its rival) for each view k of ``views`` after the pair that is judged again and has a
    rival (:func:`_rival`): not placed by the epipolar chain (its own two-view geometry placed it,
    where the others were predicted; a split chain competes with the motion prior at
    registration), with ``sound`` neighbours a < k < b, the nearest on either side (a wrong
    neighbour would predict wrong). Which views are judged is decided before the first is: a
    caller may change the model between them."""
    judged = []
    for k in (v for v in views if v not in CALIBRATED):
        view = recon.views[k]
        a = max((v for v in sound if v < k), default=None)
        b = min((v for v in sound if v > k), default=None)
        if not (a is None or b is None or view.found_by == FoundBy.EPIPOLAR_CHAIN or view.features is None
                or view.image_size is None):
            judged.append((k, a, b))
    for k, a, b in judged:
        rival = _rival(recon, settings, k, a, b)
        if rival is not None:
            yield k, rival


def _sound(recon: Reconstruction, doubted: set[int]) -> list[int]:
    return [v for v in recon.registered_views if not recon.views[v].placement_flag and v not in doubted]


def contradicted_by_neighbours(recon: Reconstruction, settings: RegistrationSettings,
                               doubted: set[int] = frozenset()) -> dict[int, Flag]:
    """{view: flag} of the registered views after the pair, not flagged at their registration
    nor in ``doubted``, whose camera a rival predicted from their neighbours contradicts (the
    module's rule; :func:`_rivals_between` says which views). Not on a rig walk (a station's two
    images are one body; their neighbours are each other)."""
    if recon.rig is not None:
        return {}
    sound = _sound(recon, doubted)
    return {k: rival.contradiction(recon) for k, rival in _rivals_between(recon, settings, sound, sound)}


@dataclass(frozen=True)
class Hindsight:
    """What judging the cameras between their neighbours did: {view: what was found} of those
    registered again (``registered_again``), :func:`contradicted_by_neighbours`'s verdicts on the
    model as it was before any (``contradicted``: they hold for the model only when nothing was
    registered again), and the global BA's report after any (``ba``, else None)."""

    registered_again: dict[int, str]
    contradicted: dict[int, Flag]
    ba: dict[str, Any] | None = None


def register_again(recon: Reconstruction, options: MapperOptions, doubted: set[int] = frozenset()) -> Hindsight:
    """Put the rival a view's neighbours find (:func:`_rival`) in that view's place, flagged
    views included, when the rival is no choice on a margin itself (no camera found there, the
    view's own included, explains ``TrustConfig.ambiguity_ratio`` of its points a period away:
    the registration's rule). The view's observations go, the neighbours' points the rival
    explains become its observations, and the camera is refined on them (the points held); a
    refinement gone astray (fewer than ``ResectionConfig.min_inliers`` of them within
    ``ransac_threshold_px``, or their RMS over ``max_rms_px``) puts the model back; one that holds
    is recorded (:meth:`Reconstruction.register_again`). After any, the model is globally adjusted
    (its outlier rounds included). Not on a rig; the paper's mode (there to reproduce its
    experiments) and a run without a final global BA (``ba="local"``) only judge."""
    if recon.rig is not None:
        return Hindsight({}, {})
    mp, rc = options.motion_prior, options.resection
    sound = _sound(recon, doubted)
    mode = mode_of(options.pipeline, recon)
    retry = mode.name != "paper" and options.pipeline.ba != "local"
    adjustment = mode.adjustment_options(recon, options)
    again, contradicted = {}, {}
    for k, rival in _rivals_between(recon, options.registering, sound, recon.registered_views if retry else sound):
        if k in sound:
            contradicted[k] = rival.contradiction(recon)
        view = recon.views[k]
        if not retry:
            continue
        if rival.margin:
            log.info("%s: the camera found between its neighbours is %s; not registered again", view.name, rival.margin)
            continue
        state = recon.checkpoint()
        recon.remove_observations(recon.obs_view == k)
        recon.remove_lonely_points()  # the points it alone put beside a neighbour's go with it
        rows, features = explaining_matches(view.features, rival.P, recon.points[rival.points], rival.desc,
                                            mp.explain_px, mp.min_zncc)
        live = recon.alive[rival.points[rows]]
        view.P = rival.P
        recon.add_observations(k, features[live], rival.points[rows[live]])
        adjust(recon, adjustment.bundle, adjustment.pipeline.camera_model, free_views=[k],
               free_points=np.zeros(0, np.int64))
        err = recon.observation_errors(recon.obs_view == k)
        fits = int(np.sum(err <= rc.ransac_threshold_px))
        if fits < rc.min_inliers or not np.sqrt(np.mean(err ** 2)) <= rc.max_rms_px:
            recon.restore(state)
            log.info("%s: refined, the camera found between its neighbours fits %d of their points; not registered "
                     "again", view.name, fits)
            continue
        again[k] = (f"{rival.where(recon)}; registered again on {fits} of them "
                    f"(first: {view.found_by}{', flagged' if view.placement_flag else ''})")
        recon.register_again(k, again[k])
        log.warning("%s: registered again between its neighbours: %s", view.name, again[k])
    if not again:
        return Hindsight(again, contradicted)
    ba, _ = adjust_globally(recon, mode.adjustment_options(recon, options))  # the zooms may have changed
    return Hindsight(again, contradicted, ba)
