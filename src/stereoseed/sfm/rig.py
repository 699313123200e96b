"""Walking with a calibrated stereo rig: both cameras at every station (issue #38).

The views interleave the stations: view ``2 s`` is station s's left image, ``2 s + 1`` its
right one; views 0 and 1 are the calibrated pair, station 0, which gives the rig (each camera's
intrinsics and the right camera's pose relative to the left, :class:`Rig`). The same mapper
loop places them, behind the same protocols:

* :class:`RigRegistrar` places a station's left image from the 2D-3D pairs of *both* its
  images with the previous station's points (a generalised resection,
  :func:`stereoseed.estimators.rig_resection.resect_rig`), and its right image by the rig from
  the left one (or, when the left one could not be placed, from its own pairs alone);
* :class:`RigMode` grows the model as the accurate mode does (the right image's matches with
  its own left image are the station's metric stereo pair) and adjusts with the rig held: one
  pose per station (:func:`stereoseed.estimators.rig_bundle.rig_bundle_adjust`), the local
  window counted in stations, then the loop closed and a global rig BA at the end.

The scale is the rig's baseline at every station: it cannot drift along the walk.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import cv2
import numpy as np

from stereoseed.arrays import unique
from stereoseed.estimators.config import BundleConfig, ResectionConfig
from stereoseed.estimators.resection import ResectionResult
from stereoseed.estimators.rig_bundle import RigBundleProblem, rig_bundle_adjust
from stereoseed.estimators.rig_resection import Rig, resect_rig, rig_reprojection_errors
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.projection import rotation_angle_deg
from stereoseed.sfm.correspondence import CorrespondenceSource
from stereoseed.sfm.loop_closure import close_loop
from stereoseed.sfm.modes import AccurateMode
from stereoseed.sfm.config import OutlierConfig, RegistrationConfig
from stereoseed.sfm.options import MapperOptions
from stereoseed.sfm.motion_prior import explained_points, hypotheses_near, pose_matrix, predict_pose, recent_points
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.refinement import global_adjust
from stereoseed.sfm.registration.base import (Candidate, FailureKind, FoundBy, Registration, RegistrationFailure,
                                              ambiguous_rivals, ambiguity_flag, chained_points)
from stereoseed.sfm.registration.ambiguity import judge_ambiguity
from stereoseed.sfm.registration.settings import RegistrationSettings

__all__ = ["RigMode", "RigRegistrar", "global_rig_adjust", "rig_adjust", "station_of", "side_of"]


def station_of(view: int) -> int:
    """The station of view ``view`` (views interleave the stations: left, right)."""
    return view // 2


def side_of(view: int) -> int:
    """0 for a station's left image, 1 for its right one."""
    return view % 2


def station_partner(view: int) -> int:
    """The other image of view ``view``'s station (it may lie past the walk's last image)."""
    return view ^ 1


def _predicted_station(recon: Reconstruction, rig: Rig, s: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Station s's pose as the walk's constant motion predicts it: from the last two placed
    stations (the steps between them counted), or after station 0 alone one rig baseline on from
    its right camera (the way the single-camera walk's first insertion extrapolates the pair)."""
    placed = sorted({station_of(v) for v in recon.registered_views if station_of(v) < s})
    if not placed:
        return None
    if len(placed) == 1:
        first = _station_pose(recon, rig, placed[0])
        T_before, T_last = pose_matrix(*first), pose_matrix(*rig.right_pose(*first))
        steps = 1
    else:
        a, b = placed[-2:]
        T_before, T_last = (pose_matrix(*_station_pose(recon, rig, i)) for i in (a, b))
        steps = max(1, round((s - b) / (b - a)))
    T = predict_pose(T_before, T_last, steps)
    return T[:3, :3], T[:3, 3]


def _station_pose(recon: Reconstruction, rig: Rig, s: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Station s's pose (the left camera's R (3, 3), t (3,)) from whichever of its views is
    registered (the left first), or None."""
    for side in (0, 1):
        v = 2 * s + side
        if v < len(recon.views) and recon.views[v].registered:
            cam = recon.views[v].camera
            return rig.left_pose(side, cam.R, cam.t)
    return None


class RigRegistrar:
    """A station's images placed together: the left image's camera from the 2D-3D pairs of both
    images with the last placed station's points (a generalised resection), the right image's
    from the left one through the rig."""

    def register(self, recon: Reconstruction, source: CorrespondenceSource, k: int,
                 found: Registration | RegistrationFailure | None,
                 settings: RegistrationSettings) -> Registration | RegistrationFailure:
        rig = recon.rig
        view = recon.views[k]
        t0 = time.perf_counter()
        if view.image_size != recon.views[side_of(k)].image_size:
            (w, h), (w1, h1) = view.image_size, recon.views[side_of(k)].image_size
            return RegistrationFailure(f"{view.name}: {w}x{h} pixels, but the rig's {'right' if side_of(k) else 'left'} "
                                       f"camera was calibrated on {w1}x{h1} images", kind=FailureKind.IMAGE_SIZE)
        cand = Candidate(k, view.name, view.image, source.features(k, view.image))
        s = station_of(k)
        if side_of(k) == 1 and recon.views[k - 1].registered:  # the left image placed the station
            R, t = _station_pose(recon, rig, s)
            return _registration(cand, rig.projections(R, t)[1], None, t0)
        # the station's images that are still to be placed, each with its 2D-3D pairs
        cands = {side_of(k): cand}
        if side_of(k) == 0 and k + 1 < len(recon.views) and recon.views[k + 1].image_size == recon.views[1].image_size:
            right = recon.views[k + 1]
            cands[1] = Candidate(k + 1, right.name, right.image, source.features(k + 1, right.image))
        placed = [v for v in recon.registered_views if station_of(v) < s]
        if not placed:
            return RegistrationFailure(f"{view.name}: no station placed before it", kind=FailureKind.TOO_FEW_MATCHES)
        last = station_of(placed[-1])
        previous = [v for v in placed if station_of(v) == last]
        # candidates for the station's pose, each from one set of 2D-3D pairs: the previous
        # station's matches under a robust F (steps of 10-20 degrees), and each set the walk's
        # predicted motion finds around the projections of the recent points (wider steps: the
        # matcher's search radius is a quarter of the image). The pose explaining the most recent
        # points in both images wins, as the single camera's motion prior decides.
        recent = recent_points(recon, previous[-1], settings.motion_prior.recent_views)
        pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (X, x, side) per set
        matches = 0
        chained_sets = []
        matched = {}  # side -> (the previous station's image of that side, their matches)
        for sd in sorted(cands, reverse=True):  # the right image first: its match was computed ahead (next_match)
            p = next((v for v in previous if side_of(v) == sd), previous[-1])
            vp = recon.views[p]
            matched[sd] = p, source.match(p, cands[sd].index, vp.features, cands[sd].features, None, vp.image_size[0])
        for sd, c in cands.items():  # each image with the previous station's image of its side
            p, m = matched[sd]
            pid, chained = chained_points(recon, p, m)
            matches += len(m)
            chained_sets.append((recon.points[pid[chained]], c.features.points[m.idx2[chained]],
                                 np.full(int(chained.sum()), sd)))
        pairs.append(tuple(np.concatenate(a) for a in zip(*chained_sets)))
        predicted = _predicted_station(recon, rig, s)
        trusted = settings.motion_prior.trusted_chain_factor * settings.resection.min_inliers * len(cands)
        if predicted is not None and len(pairs[0][0]) < trusted:  # a strong chain needs no prediction
            P_predicted = rig.projections(*predicted)
            for sd, c in cands.items():
                for hyps in hypotheses_near(recon, P_predicted[sd], c.features, settings.motion_prior,
                                            settings.resection, recent):
                    pairs += [(h.points3d, h.points2d, np.full(len(h), sd)) for h in hyps]
        # a pose per set: the robust-F set from both images at once, each predicted set by P3P in its image
        poses = []
        if len(pairs[0][0]) >= settings.registration.min_chained_points:
            first = resect_rig(rig, *pairs[0], what=f"station {s} ({view.name})")
            if first.success:
                poses.append((first.R, first.t))
        poses += [pose for ps in pairs[1:]
                  if (pose := _pose_from_one_image(rig, *ps, settings.registration, settings.resection)) is not None]
        n_pairs = sum(len(ps[0]) for ps in pairs)
        if not poses:
            return RegistrationFailure(f"{view.name}: station {s}: no pose from its images' {n_pairs} matches with "
                                       f"reconstructed points", matches, n_pairs, kind=FailureKind.NO_CAMERA)
        mp = settings.motion_prior
        counts = np.zeros(len(poses), np.int64)
        cameras = [rig.projections(*pose) for pose in poses]  # each pose's (P_left, P_right)
        for sd, c in cands.items():
            counts += explained_points(c.features, [P[sd] for P in cameras],
                                       recon.points[recent[0]], recent[1], mp.explain_px, mp.min_zncc)
        best = int(np.argmax(counts))
        rivals = ambiguous_rivals(recon, previous[-1], recent[0], [P[0] for P in cameras], counts, best, settings.trust)
        # the winner refitted on every pair of both images it explains, from all sets
        X, x, side = (np.concatenate(a) for a in zip(*pairs))
        err, in_front = rig_reprojection_errors(rig, *poses[best], X, x, side)
        agree = (err <= 2 * settings.resection.ransac_threshold_px) & in_front
        res = resect_rig(rig, X[agree], x[agree], side[agree], what=f"station {s} ({view.name})")
        if not res.success:
            return RegistrationFailure(f"{view.name}: station {s}: {res.reason}", matches, n_pairs,
                                       kind=FailureKind.NO_CAMERA)
        reg = _registration(cand, res.projections()[side_of(k)], (res, matches, n_pairs), t0)
        if rivals:
            # judged as a single camera's choice is, on this image and the previous station's of its side
            reg = dataclasses.replace(reg, flag=ambiguity_flag(rivals, counts, best),
                                      rivals=tuple(cameras[j][side_of(k)] for j, _, _ in rivals))
            reg = judge_ambiguity(recon, matched[side_of(k)][0], reg, settings, source)
        return reg


def _pose_from_one_image(rig: Rig, X: np.ndarray, x: np.ndarray, side: np.ndarray,
                         registration: RegistrationConfig, resection: ResectionConfig
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """The station pose (R, t of its left camera) from 2D-3D pairs X (N, 3), x (N, 2) of one of its
    images (``side`` (N,), all alike): P3P in RANSAC (OpenCV) with that camera's calibrated K,
    carried to the left camera through the rig; None when too few pairs agree."""
    if len(X) < max(registration.min_chained_points, 4):
        return None
    sd = int(side[0])
    # OpenCV's RANSAC registrator seeds its own generator: deterministic without cv2.setRNGSeed
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, x, rig.Ks[sd], None, iterationsCount=int(resection.ransac_max_iters),
                                             reprojectionError=2 * resection.ransac_threshold_px,
                                             confidence=resection.ransac_confidence, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < resection.min_inliers:
        return None
    return rig.left_pose(sd, cv2.Rodrigues(rvec)[0], tvec.ravel())


def _registration(cand: Candidate, P: np.ndarray, resected, t0: float) -> Registration:
    """The Registration of ``cand`` with camera P (the rig's calibrated intrinsics); resected:
    (the station's rig resection, matches, 2D-3D pairs) or None when the station's other image
    placed it."""
    if resected is None:
        result = ResectionResult(Camera(P, CameraModel.FIXED), np.zeros(0, bool), 0.0, 0,
                                 {"n_pairs": 0, "n_inliers": 0, "model": CameraModel.FIXED})
        return Registration(cand, result, FoundBy.RIG, 0, 0, seconds={"total": time.perf_counter() - t0},
                            notes={"station_placed_by": "its other image, through the rig"})
    res, matches, chained = resected
    result = ResectionResult(Camera(P, CameraModel.FIXED), res.inliers, res.rms_px, res.n_hypotheses,
                             {"n_pairs": int(len(res.inliers)), "n_inliers": int(res.inliers.sum()),
                              "model": CameraModel.FIXED, "inliers_per_side": list(res.n_inliers)})
    return Registration(cand, result, FoundBy.RIG, matches, chained, seconds={"total": time.perf_counter() - t0})


def rig_adjust(recon: Reconstruction, free_stations: list[int], refine: bool = False) -> dict[str, Any] | None:
    """Bundle-adjust the stations ``free_stations`` (station 0, the calibration, never moves) and
    every point their images see, with the rig held: one pose per station, its two cameras the
    rig's. Observations of those points in other stations' images pin them. Writes the registered
    views' cameras and the points back; returns a JSON-able report (None: nothing to adjust).
    refine: the rig's relative pose refined too (``recon.rig`` becomes the refined rig)."""
    rig = recon.rig
    free_stations = [s for s in free_stations if s > 0]
    registered = np.zeros(len(recon.views), bool)
    registered[recon.registered_views] = True
    in_free = np.isin(recon.obs_view // 2, free_stations) & registered[recon.obs_view]
    points = unique(recon.obs_point[in_free & recon.alive[recon.obs_point]])
    if not len(points):
        return None
    involved = np.isin(recon.obs_point, points) & registered[recon.obs_view]
    obs_view = recon.obs_view[involved]
    stations = unique(obs_view // 2)
    poses = [_station_pose(recon, rig, int(s)) for s in stations]
    problem = RigBundleProblem(
        rig=rig, R=np.stack([p[0] for p in poses]), t=np.stack([p[1] for p in poses]),
        points=recon.points[points], obs_station=np.searchsorted(stations, obs_view // 2), obs_side=obs_view % 2,
        obs_point=np.searchsorted(points, recon.obs_point[involved]), obs_xy=recon.observation_xy(involved),
        free_stations=np.isin(stations, free_stations), refine_rig=refine)
    result = rig_bundle_adjust(problem)
    if refine:
        recon.rig = result.rig
    cams = result.projections()
    for i, s in enumerate(stations):
        if problem.free_stations[i]:
            for sd in (0, 1):
                v = 2 * int(s) + sd
                if v < len(recon.views) and registered[v]:
                    recon.views[v].P = cams[i, sd]
    recon.points[points] = result.points
    refined = {"rig_refined": {"angle_change_deg": rotation_angle_deg(result.rig.R_rl, rig.R_rl),
                               "baseline": result.rig.baseline}} if refine else {}
    return {**refined, "free_stations": int(problem.free_stations.sum()), "free_points": int(len(points)),
            "observations": int(involved.sum()), "iterations": result.iterations, "seconds": result.seconds,
            "rms_before_px": result.rms_before, "rms_after_px": result.rms_after}


class RigMode(AccurateMode):
    """The accurate mode's tracks and points, adjusted with the rig held (module docstring)."""

    name = "rig"

    def local_adjust(self, recon: Reconstruction, prev: int, k: int, new_points: np.ndarray,
                     chain_points: np.ndarray, options: MapperOptions) -> dict[str, Any]:
        """After a station's last image: the last ``window`` stations (the local BA's window
        counted in stations). A left image whose right one comes next waits for it: one BA per
        station."""
        if side_of(k) == 0 and k + 1 < len(recon.views) and recon.views[k + 1].status == "pending":
            return {"skipped": True, "reason": "the station's right image comes next"}
        placed = sorted({station_of(v) for v in recon.registered_views})
        report = rig_adjust(recon, placed[-options.pipeline.window:])
        return {"skipped": True} if report is None else report

    def adjustment_options(self, recon: Reconstruction, options: MapperOptions) -> MapperOptions:
        """The rig's calibrated intrinsics: the "fixed" model (what the cameras' uncertainty uses)."""
        return options.held()

    def next_match(self, k: int) -> int | None:
        """A right image: the next station's right one (:class:`RigRegistrar` asks for that match
        first). A left image's interest points still grow when its right one is tracked back."""
        return k + 2 if side_of(k) == 1 else None

    def finish(self, recon: Reconstruction, options: MapperOptions, source: CorrespondenceSource) -> dict[str, Any]:
        """The loop closed as the accurate mode closes it (the last stations' images matched
        against the first ones', points merged and linked), then a global rig BA
        (:func:`global_rig_adjust`) unless closing the loop ran one."""
        out: dict[str, Any] = {}
        adjusted = False
        def adjust(r: Reconstruction) -> tuple[dict[str, Any], int]:
            return global_rig_adjust(r, options.bundle, options.outliers, options.pipeline.refine_rig)

        if options.pipeline.loop_closure:
            adjusted, out["loop_closure"] = close_loop(recon, options.loop_closure, options.resection, source, adjust)
        if not adjusted:
            out["final_ba"] = adjust(recon)[0]
        return out


def global_rig_adjust(recon: Reconstruction, bundle: BundleConfig, outliers: OutlierConfig,
                      refine_rig: bool) -> tuple[dict[str, Any], int]:
    """:func:`stereoseed.sfm.refinement.global_adjust`'s rounds with every station adjusted with
    the rig held (the rig refined in the first round with ``PipelineConfig.refine_rig``)."""
    stations = sorted({station_of(v) for v in recon.registered_views})
    # (the camera model: the rig's calibrated intrinsics; rig_adjust holds them whatever it is)
    return global_adjust(recon, bundle, outliers, CameraModel.FIXED,
                         lambda r, i: rig_adjust(r, stations, refine=refine_rig and i == 0))
