"""One or more cameras calibrated from their views of a target: each camera's K and lens, every
view's pose, the target's faces where they really are, and a fixed stereo rig's relative pose.

How (the fitting itself in :mod:`stereoseed.calibration.stages`, each step's reason there):

1. Views that cannot be used are set aside with their reason (no target, too few corners, a
   view of another size; later, a view that disagrees with the others); the calibration goes on
   while enough remain.
2. Each camera on its own, every face of every view taken as a flat board (``flat_stage``):
   Zhang's closed form (:mod:`stereoseed.calibration.intrinsics`), then a fit of the intrinsics,
   the lens and a pose per board. Nothing here depends on how the faces were assembled.
3. Everything together (:mod:`stereoseed.calibration.refine_target`): the cameras, every view's
   pose, each face's pose on the target where the photos show it off its nominal place (BIC;
   never with ``rigid_target``).
4. Each camera's intrinsics from 3 are checked against 2's (:func:`_consistency`): a target that
   is not the rigid body 3 assumes biases them, and that camera keeps 2's; 3 again.
5. A rig (:mod:`stereoseed.calibration.rig_check`): the shots' relative poses from 3 checked
   against each other (refused when most disagree: photos not listed in the same order); one
   relative pose for all the shots the cameras took together, each camera's intrinsics held at
   3's (with a long lens the principal point trades against the rig's rotation); its uncertainty
   from a jackknife over shots that re-estimates the intrinsics too, the shots' pull on the
   intrinsics and the pose against the single shots and the faces' PnP judged (warnings, or
   refused with ``strict``).
6. Each camera is checked to be a physical one (:func:`stereoseed.calibration.config.camera_problems`),
   its RMS judged (a warning, or refused above ``CalibrationConfig.max_rms_px``).

The target's frame is face 0's nominal frame (or, for faces never seen together with face 0,
their own group's lowest face's): the cameras come out in the target's unit (mm).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.calibration import poses as rt
from stereoseed.calibration.config import CalibrationConfig, camera_problems, chi2_quantile_4
from stereoseed.calibration.detection import Detection
from stereoseed.calibration.refine_target import Problem, Solution, intrinsics_covariance, projections
from stereoseed.calibration.rig_check import RigResult, check_shots, judge, shot_poses, view_poses
from stereoseed.calibration.stages import (ViewResult, blur_first, fit, flat_stage, joint_problem, rms, view_errors, view_key,
                                          view_of)
from stereoseed.calibration.target import Target
from stereoseed.errors import StereoseedError

log = logging.getLogger(__name__)

__all__ = ["ViewResult", "CameraResult", "RigResult", "Calibration", "calibrate_cameras", "camera_entry", "calibration_json"]


@dataclass
class CameraResult:
    K: np.ndarray
    lens: np.ndarray  # k1, k2, p1, p2, k3
    image_size: tuple[int, int]
    rms_px: float  # over the corners of every view used
    n_points: int
    coverage: float  # share of the frame the corners of its views cover
    views: list[ViewResult]
    known: bool = False  # intrinsics given, not estimated
    # the whole model's fx, fy, cx, cy against the faces' one by one: (chi-square, its limit)
    consistency: tuple[float, float] | None = None
    from_faces: bool = False  # the intrinsics are the faces' one by one (the consistency test failed)


@dataclass
class Calibration:
    cameras: list[CameraResult]
    target: Target  # the faces where they were found to be
    face_moves: list[tuple[float, float] | None]  # per face: (mm, deg) from nominal; None: not estimated
    rig: RigResult | None = None
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # how the answer was reached, where it is not the usual way

    def pair(self, camera: int) -> ViewResult:
        """The view that starts the sequence (each camera's first)."""
        return self.cameras[camera].views[0]


# ---------------------------------------------------------------- helpers
def _coverage(views: list[ViewResult], size: tuple[int, int]) -> float:
    """The share of the frame inside the convex hulls of the views' corners (on a 1/8 grid)."""
    scale = 8
    mask = np.zeros((size[1] // scale + 1, size[0] // scale + 1), np.uint8)
    for v in views:
        if v.used and len(v.detection) >= 3:
            hull = cv2.convexHull((v.detection.pixels / scale).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 1)
    return float(mask.mean())


def _check_views(views: list[list[ViewResult]], pair: bool, labels: list[str]) -> None:
    """Set aside views of another size or given twice; refuse when the pair's own view is not
    usable (it is the camera the sequence starts from)."""
    for c, cam in enumerate(views):
        # the size of the pair's photo, or else of the first photo showing the target
        first = cam[0] if pair else next((v for v in cam if v.used), cam[0])
        size, seen = first.detection.image_size, {}
        for i, v in enumerate(cam):
            if v.used and v.detection.image_size != size:
                w, h = v.detection.image_size
                v.reason = f"{w}x{h} pixels, but {first.name} is {size[0]}x{size[1]}: not this camera's image"
            elif v.used and v.name in seen:
                v.reason = f"the same image as view {seen[v.name] + 1} of {labels[c]}"
            seen.setdefault(v.name, i)
        if pair and not cam[0].used:
            raise StereoseedError(f"{cam[0].name}: {cam[0].reason}")
        if not any(v.used for v in cam):
            raise StereoseedError(f"{labels[c]}: no usable view ({cam[0].name}: {cam[0].reason})")


def calibrate_cameras(target: Target, detections: list[list[Detection]], rig: bool = False, rigid_target: bool = False,
                      k3: bool = False, known: list[tuple[np.ndarray, np.ndarray] | None] | None = None,
                      cfg: CalibrationConfig = CalibrationConfig(), pair: bool = True, leave_one_out: bool = True,
                      labels: list[str] | None = None) -> Calibration:
    """Calibrate the cameras that took ``detections`` (per camera, its views' detections; with
    ``pair`` each camera's first view is the stereo pair's, which cannot be left out).

    ``rig``: the cameras are fixed to each other and took their i-th views together (the same
    number of views each): one relative pose for all. ``rigid_target``: the faces stay where
    target.json puts them. ``known``: per camera, (K, lens) given, or None to estimate them.
    Raises :class:`StereoseedError` when a camera cannot be calibrated (with the reason)."""
    C = len(detections)
    labels = labels or [f"camera {c + 1}" for c in range(C)]
    known = list(known or [None] * C)
    if rig and (C < 2 or len({len(d) for d in detections}) != 1):
        raise StereoseedError("--rig: the cameras must have taken the same number of views, the i-th of each together "
                              f"(got {', '.join(str(len(d)) for d in detections)})")
    views = [[ViewResult(d.name, c, d, d.problem()) for d in dets] for c, dets in enumerate(detections)]
    _check_views(views, pair, labels)
    flat = [flat_stage(target, views[c], known[c], k3, cfg, labels[c], pair) for c in range(C)]
    # step 3 with every view on its own; the intrinsics checked against step 2's; a rig from there
    problem, sol, shots = _solve_all(target, views, flat, False, rigid_target, known, k3, cfg, pair)
    tests = _consistency(problem, sol, flat, cfg)
    held = [c for c, test in enumerate(tests) if test is not None and test[0] > test[1]]
    fixed = [(flat[c][0], flat[c][1]) if c in held else known[c] for c in range(C)]
    if held:
        problem, sol, shots = _solve_all(target, views, flat, False, rigid_target, fixed, k3, cfg, pair)
    per_camera = (problem, sol)
    if rig:
        relative = shot_poses(problem, sol, shots)
        agreeing = check_shots(relative, cfg, {i: (views[0][i].name, views[1][i].name) for i in relative})
        relative = {i: relative[i] for i in agreeing}  # the single shots' evidence, each shot's own relative pose
        prior = (view_poses(problem, sol, shots), sol.state.faces)
        # each camera's intrinsics as its own views determine them, held: free, the rig's fit would
        # trade a long lens's principal point against the rig's rotation (rig_check); what the
        # shots would pull them to is judged after
        own = [(sol.state.K[c].copy(), sol.state.lens[c].copy()) for c in range(C)]
        start = [(own[c][0], own[c][1], *flat[c][2:]) for c in range(C)]  # the poses, cov, lens terms
        problem, sol, shots = _solve_all(target, views, start, True, rigid_target, own, k3, cfg, pair, prior)
    cal = _results(target, views, problem, sol, shots, rig, rigid_target, known, cfg, labels, pair)
    if rig:
        covariance = [None if known[c] is not None else flat[c][3] if c in held else
                      intrinsics_covariance(*per_camera, c) for c in range(C)]
        judge(cal.rig, views, (problem, sol, shots), per_camera, flat, [c in held for c in range(C)], covariance,
              relative, cfg, labels, leave_one_out)
        cal.warnings += cal.rig.warnings
    for c, test in enumerate(tests):
        cal.cameras[c].consistency, cal.cameras[c].from_faces = test, c in held
        if c in held:
            cal.notes.append(f"{labels[c]}: the target's faces do not fit together as one rigid body as well as each "
                             f"fits on its own (intrinsics chi-square {test[0]:.0f}, limit {test[1]:.0f}: a face not "
                             "flat, the target flexed): its intrinsics are those of its faces taken one by one")
    if rig:
        cal.notes += cal.rig.notes
    return cal


def _solve_all(target: Target, views: list[list[ViewResult]], flat: list[tuple], rig: bool, rigid: bool, known: list,
               k3: bool, cfg: CalibrationConfig, pair: bool, prior: tuple | None = None) -> tuple[Problem, Solution, list]:
    """Step 3: the joint fit, then again without the views it does not explain, until none is left.
    A rig starts from ``prior``, its cameras fitted as independent views (:func:`joint_problem`)."""
    problem, state, shots = joint_problem(target, views, flat, rig, rigid, known, k3, prior)
    sol = fit(problem, state, cfg)
    while True:
        per_view = {k: rms(e) for k, e in view_errors(problem, sol).items()}
        median = float(np.median(list(per_view.values())))
        limit = max(cfg.view_outlier_min_px, cfg.view_outlier_factor * median)
        bad = [k for k, r in per_view.items() if r > limit and not (pair and view_of(k)[1] == 0)]
        if not bad:
            return problem, sol, shots
        cause = ("another camera's image, a moved lens, a target that moved between the rig's two exposures, or two "
                 "photos not taken together (listed out of order)" if rig else "another camera's image or a moved lens")
        for k in bad:
            c, i = view_of(k)
            views[c][i].reason = (f"its corners reproject at {per_view[k]:.1f} px while the views reproject at "
                                  f"{median:.2f} px (median): {blur_first(views[c][i], cause)}")
        problem, state, shots = joint_problem(target, views, flat, rig, rigid, known, k3, prior)
        state.K, state.lens, state.rig = sol.state.K, sol.state.lens, sol.state.rig
        sol = fit(problem, state, cfg)


def _consistency(problem: Problem, sol: Solution, flat: list[tuple], cfg: CalibrationConfig
                 ) -> list[tuple[float, float] | None]:
    """Per camera whose intrinsics were estimated, the chi-square of the whole model's fx, fy, cx,
    cy against its faces' one by one (step 2) over step 2's covariance, and the limit
    (cfg.consistency_quantile of chi-square with 4 degrees of freedom)."""
    if cfg.consistency_quantile is None:
        return [None] * problem.n_cameras
    limit = chi2_quantile_4(cfg.consistency_quantile)
    out: list[tuple[float, float] | None] = []
    for c in range(problem.n_cameras):
        cov = flat[c][3]
        # the test holds only between the same camera models: step 2 with too few boards for a
        # lens fits none, and its intrinsics then carry the lens's error, not the target's
        if cov is None or not problem.free_intrinsics[c] or flat[c][4] != problem.n_lens:
            out.append(None)
            continue
        K0, K1 = flat[c][0], sol.state.K[c]
        delta = np.array([K1[0, 0] - K0[0, 0], K1[1, 1] - K0[1, 1], K1[0, 2] - K0[0, 2], K1[1, 2] - K0[1, 2]])
        out.append((float(delta @ np.linalg.pinv(cov) @ delta), limit))
    return out


def _results(target: Target, views: list[list[ViewResult]], problem: Problem, sol: Solution, shots: list, rig: bool,
             rigid: bool, known: list, cfg: CalibrationConfig, labels: list[str], pair: bool) -> Calibration:
    state = sol.state
    face_poses = [rt.to_rt(p[:6]) for p in state.faces]
    projected = projections(problem, state)
    per_view_groups: dict[int, list[int]] = {}
    for n, g in enumerate(problem.groups):
        per_view_groups.setdefault(g.view, []).append(n)
    for s, members in enumerate(shots):
        for c, i in members:
            v = views[c][i]
            pose = rt.compose(state.rig[c], state.shots[s])
            if problem.local[s]:
                face = int(problem.groups[per_view_groups[view_key(c, i)][0]].face)
                pose = rt.compose(pose, rt.inverse(state.faces[face, :6]))
            v.R, v.t = rt.to_rt(pose)
            det, out = v.detection, np.zeros_like(v.detection.pixels)
            for n in per_view_groups.get(view_key(c, i), []):
                g = problem.groups[n]
                out[det.face == g.face] = projected[n]
            v.reprojected = out
            err = np.linalg.norm(out - det.pixels, axis=1)
            v.rms_px = float(np.sqrt(np.mean(err * err)))
    cameras, warnings = [], []
    for c, cam in enumerate(views):
        used = [v for v in cam if v.used]
        errors = np.concatenate([np.linalg.norm(v.reprojected - v.detection.pixels, axis=1) for v in used])
        size = used[0].detection.image_size
        result = CameraResult(state.K[c].copy(), state.lens[c].copy(), size, float(np.sqrt(np.mean(errors ** 2))),
                              len(errors), _coverage(cam, size), cam, known[c] is not None)
        if known[c] is None:
            problems = camera_problems(result.K, result.lens, size, cfg)
            if problems:
                raise StereoseedError(f"{labels[c]}: refused, no physical camera: {'; '.join(problems)}. The views do not "
                                      "determine it: add views with the target at other angles and in other parts of "
                                      "the frame, or give the camera's intrinsics")
        cameras.append(result)
        if result.rms_px > cfg.warn_rms_px or (cfg.max_rms_px is not None and result.rms_px > cfg.max_rms_px):
            cause = ("the target may not be where target.json puts its faces: try without --rigid-target, which "
                     "estimates where they are" if rigid else
                     "blurred views, or pixels that are not the target's corners: look at the check images")
            message = f"{labels[c]}: the corners reproject with {result.rms_px:.2f} px RMS; {cause}"
            if cfg.max_rms_px is not None and result.rms_px > cfg.max_rms_px:
                raise StereoseedError(f"{message} (--max-rms {cfg.max_rms_px:g})")
            warnings.append(message)
        for v in used:  # one bad photo among good ones leaves the camera's RMS under the limit: it is named
            if v.rms_px > cfg.warn_rms_px and result.rms_px <= cfg.warn_rms_px:
                warnings.append(f"{labels[c]}, {v.name}: its corners reproject with {v.rms_px:.2f} px RMS (the camera's: "
                                f"{result.rms_px:.2f} px); {blur_first(v, 'pixels that are not the target corners')}: "
                                "look at its check image")
        if pair and not target.planar and len(cam[0].detection.faces_found) == 1:
            warnings.append(f"{labels[c]}: the pair's photo {cam[0].name} shows one face of the target: the camera's "
                            "pose (its P) is determined less well than from two or three faces in view")
    moves: list[tuple[float, float] | None] = []
    for f, face in enumerate(target.faces):
        if not problem.free_faces[f]:
            moves.append(None)
            continue
        R, t = face_poses[f]
        centre = face.corners3d().mean(axis=0)
        moves.append((float(np.linalg.norm(R @ centre + t - centre)), rt.angle_deg(state.faces[f, :6])))
    rig_result = None
    if rig:
        R, t = rt.to_rt(state.rig[1])
        rig_result = RigResult(R, t, sum(1 for s in shots if len({c for c, _ in s}) > 1))
    return Calibration(cameras, target.moved(face_poses), moves, rig_result, warnings)


def camera_entry(cal: Calibration, c: int) -> dict:
    """calib.json's entry of camera c: the pair view's P = K [R | t] (undistorted pixels, the
    target's frame), K, R, t, the lens, the image size, and how well its views fit."""
    cam, view = cal.cameras[c], cal.pair(c)
    P = cam.K @ np.hstack([view.R, view.t[:, None]])
    used = [v for v in cam.views if v.used]
    return {"P": P.tolist(), "K": cam.K.tolist(), "R": view.R.tolist(), "t": view.t.tolist(),
            "distortion": cam.lens.tolist(), "image_size": list(cam.image_size), "rms_px": view.rms_px,
            "n_points": len(view.detection), "camera_rms_px": cam.rms_px, "intrinsics_given": cam.known,
            "lens_views": len(used), "lens_views_rms_px": [v.rms_px for v in used],
            "skipped_views": {v.name: v.reason for v in cam.views if not v.used}}


def calibration_json(cal: Calibration) -> dict:
    """calib.json: the cameras (:func:`camera_entry`), where the target's faces were found to be
    and, for a rig, its relative pose."""
    out: dict = {"cameras": [camera_entry(cal, c) for c in range(len(cal.cameras))],
                 "unit": cal.target.unit}  # the model a run makes is metric in it (report.html's unit)
    out["target_faces"] = [{"face": f, "moved_mm": None if m is None else m[0], "turned_deg": None if m is None else m[1]}
                           for f, m in enumerate(cal.face_moves)]
    if cal.rig is not None:
        out["rig"] = cal.rig.as_json()
    for c, cam in enumerate(cal.cameras):
        if cam.consistency is not None:
            out["cameras"][c]["rigid_target_chi2"] = {"value": cam.consistency[0], "limit": cam.consistency[1],
                                                      "intrinsics_from_faces_one_by_one": cam.from_faces}
    if cal.notes:
        out["notes"] = cal.notes
    if cal.warnings:
        out["warnings"] = cal.warnings
    return out
