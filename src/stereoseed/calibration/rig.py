"""One or more cameras calibrated from their views of a target: each camera's K and lens, every
view's pose, the target's faces where they really are, and a fixed stereo rig's relative pose.

How (each step's reason in its function):

1. Views that cannot be used are set aside with their reason (no target, too few corners, a
   view that disagrees with the camera's others); the calibration goes on while enough remain.
2. Each camera on its own, every face of every view taken as a flat board (:func:`_flat_stage`):
   Zhang's closed form (:mod:`stereoseed.calibration.intrinsics`), then a fit of the intrinsics,
   the lens and a pose per board. Nothing here depends on how the faces were assembled.
3. Everything together (:mod:`stereoseed.calibration.refine_target`): the cameras, every shot's
   pose, each face's pose on the target (unless ``rigid_target``), the rig's relative pose.
4. Each camera is checked to be a physical one (:func:`stereoseed.calibration.config.camera_problems`).

The target's frame is face 0's nominal frame (or, for faces never seen together with face 0,
their own group's lowest face's): the cameras come out in the target's unit (mm).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.calibration import poses as rt
from stereoseed.calibration.config import CalibrationConfig, camera_problems
from stereoseed.calibration.detection import MIN_FACE_CORNERS, Detection
from stereoseed.calibration.intrinsics import (MIN_HOMOGRAPHY_CORNERS, homography, plane_coordinates,
                                               pose_from_homography, zhang_intrinsics, face_frame)
from stereoseed.calibration.refine_target import Group, Problem, State, Solution, projections, residuals, solve
from stereoseed.calibration.target import Target
from stereoseed.errors import StereoseedError

log = logging.getLogger(__name__)

__all__ = ["ViewResult", "CameraResult", "RigResult", "Calibration", "calibrate_cameras", "camera_entry", "calibration_json"]


@dataclass
class ViewResult:
    """One photo: where its camera was (R, t: camera from target, mm), how well it fits."""
    name: str
    camera: int
    detection: Detection
    reason: str | None = None  # why it was not used (None: used)
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    rms_px: float = float("nan")
    reprojected: np.ndarray | None = None  # (N, 2) where the calibrated camera puts each corner

    @property
    def used(self) -> bool:
        return self.reason is None


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


@dataclass
class RigResult:
    """Camera c's pose from camera 0's (R, t: X_c = R X_0 + t) and, leave-one-shot-out, how far
    it moves: the largest change of t (mm) and of the rotation (degrees)."""
    R: np.ndarray
    t: np.ndarray
    shots: int
    spread_mm: float | None = None
    spread_deg: float | None = None

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.t))

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(cv2.Rodrigues(self.R)[0])))


@dataclass
class Calibration:
    cameras: list[CameraResult]
    target: Target  # the faces where they were found to be
    face_moves: list[tuple[float, float] | None]  # per face: (mm, deg) from nominal; None: not estimated
    rig: RigResult | None = None
    warnings: list[str] = field(default_factory=list)

    def pair(self, camera: int) -> ViewResult:
        """The view that starts the sequence (each camera's first)."""
        return self.cameras[camera].views[0]


# ---------------------------------------------------------------- helpers
def _huber(errors: list[np.ndarray], cfg: CalibrationConfig) -> float:
    """Huber's threshold from the corners' errors: a robust sigma of the 2D error (its median
    over 1.1774, the Rayleigh distribution's) times cfg.huber_sigmas, at least huber_min_px."""
    e = np.concatenate(errors) if errors else np.zeros(1)
    return max(cfg.huber_min_px, cfg.huber_sigmas * float(np.median(e)) / 1.1774)


@dataclass
class _Corners(Group):
    refined: np.ndarray | None = None  # (N,) bool: the corner's sub-pixel fit succeeded


def _set_sigmas(problem: Problem, errors: list[np.ndarray] | None) -> None:
    """Each corner's error scale: 1 for a fitted corner; for one left at OpenCV's position, how
    much larger its errors are (the robust sigmas of the two kinds' errors, both from the same
    fit), so that blurred corners count for what they are worth, on any camera."""
    ratio = 1.0
    if errors is not None:
        fitted = np.concatenate([e[g.refined] for g, e in zip(problem.groups, errors)])
        other = np.concatenate([e[~g.refined] for g, e in zip(problem.groups, errors)])
        if len(other) >= _MIN_CLASS_CORNERS and len(fitted) >= _MIN_CLASS_CORNERS:
            ratio = max(1.0, float(np.median(other)) / max(float(np.median(fitted)), 1e-12))
    for g in problem.groups:
        g.sigma = np.where(g.refined, 1.0, ratio)


# corners of a kind (fitted, or left at OpenCV's position) needed to measure that kind's errors
_MIN_CLASS_CORNERS = 20


def _robust_solve(problem: Problem, state: State, cfg: CalibrationConfig) -> Solution:
    """Solved twice: with every corner alike and Huber's threshold from the start's errors, then
    with each kind of corner at its own scale and the threshold from the first answer's errors."""
    _set_sigmas(problem, None)
    sol = solve(problem, state, _huber(residuals(problem, state), cfg), cfg.max_iterations)
    _set_sigmas(problem, sol.errors)
    return solve(problem, sol.state, _huber([e / g.scale() for g, e in zip(problem.groups, sol.errors)], cfg),
                 cfg.max_iterations)


def _rms(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.zeros(0)
    return float(np.sqrt(np.mean(e * e))) if len(e) else float("nan")


def _coverage(views: list[ViewResult], size: tuple[int, int]) -> float:
    """The share of the frame inside the convex hulls of the views' corners (on a 1/8 grid)."""
    scale = 8
    mask = np.zeros((size[1] // scale + 1, size[0] // scale + 1), np.uint8)
    for v in views:
        if v.used and len(v.detection) >= 3:
            hull = cv2.convexHull((v.detection.pixels / scale).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 1)
    return float(mask.mean())


def _undistorted(pixels: np.ndarray, K: np.ndarray, lens: np.ndarray) -> np.ndarray:
    if not np.any(lens):
        return pixels
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, lens, P=K).reshape(-1, 2)


def _group(camera: int, shot: int, face: int, view: int, det: Detection, idx: np.ndarray) -> "_Corners":
    refined = det.refined[idx] if det.refined is not None else np.ones(len(idx), bool)
    return _Corners(camera, shot, face, view, det.points3d[idx], det.pixels[idx], refined=refined)


def _face_groups(det: Detection) -> list[tuple[int, np.ndarray]]:
    """(face, indices of its corners) for each face the view holds enough corners of."""
    return [(f, np.flatnonzero(det.face == f)) for f in np.unique(det.face)
            if np.count_nonzero(det.face == f) >= MIN_FACE_CORNERS]


# ---------------------------------------------------------------- step 2: every face a flat board
def _flat_stage(target: Target, views: list[ViewResult], known: tuple | None, k3: bool, cfg: CalibrationConfig,
                what: str, keep_first: bool) -> tuple[np.ndarray, np.ndarray, dict[tuple[int, int], np.ndarray]]:
    """One camera's K, lens and, per (view, face), the pose that maps the face's nominal points
    into the camera. Views that disagree with the others are marked unused (never the first
    when ``keep_first``: the pair's view, judged by the whole calibration)."""
    size = views[0].detection.image_size
    K = None if known is None else known[0]
    lens = np.zeros(5) if known is None else known[1]
    boards = []  # (view index, face, corner indices, homography or None)
    for i, v in enumerate(views):
        if v.used:
            for f, idx in _face_groups(v.detection):
                det = v.detection
                plane = plane_coordinates(target.faces[f], det.points3d[idx])
                H = homography(plane, _undistorted(det.pixels[idx], K, lens) if K is not None else det.pixels[idx])
                boards.append((i, f, idx, H if len(idx) >= MIN_HOMOGRAPHY_CORNERS or K is not None else None))
    if K is None:
        if target.planar and len({i for i, *_ in boards}) < cfg.min_flat_views:
            raise StereoseedError(f"{what}: {len({i for i, *_ in boards})} usable view(s) of a flat target; its focal "
                                  f"length and principal point need at least {cfg.min_flat_views} views at different "
                                  "angles, or the camera's intrinsics given (--intrinsics)")
        K = zhang_intrinsics([H for *_, H in boards if H is not None], size)
        if K is None:
            raise StereoseedError(f"{what}: the views do not determine the camera (no face seen well enough: at least "
                                  f"{MIN_HOMOGRAPHY_CORNERS} corners over two rows); take sharper views, closer")
        log.debug("%s: closed-form K %s", what, np.round(K, 1).tolist())
    poses: dict[tuple[int, int], np.ndarray] = {}
    for i, f, idx, H in boards:
        if H is not None:
            Rp, tp = pose_from_homography(H, K)
            O, F = face_frame(target.faces[f])
            R = Rp @ F.T
            poses[(i, f)] = rt.from_rt(R, tp - R @ O)
    for i, f, idx, H in boards:  # a face too small for its own homography: its view's other face's pose
        if H is None and (i, f) not in poses:
            other = next((p for (j, g), p in poses.items() if j == i), None)
            if other is not None:
                poses[(i, f)] = other
    keys = sorted(poses)
    corners = {(i, f): idx for i, f, idx, _ in boards}
    groups = [_group(0, s, f, i, views[i].detection, corners[i, f]) for s, (i, f) in enumerate(keys)]
    free = np.array([known is None])
    problem = Problem(groups, 1, len(target.faces), len(keys), np.ones(len(keys), bool), np.zeros(len(target.faces), bool),
                      free, np.zeros(1, bool), n_lens=0)
    state = State(K[None].copy(), lens[None].copy(), np.zeros((1, 6)), np.zeros((len(target.faces), 6)),
                  np.array([poses[k] for k in keys]))
    enough = len(keys) >= cfg.min_flat_views
    for n_lens in ((0, 5 if k3 else 4) if known is None and enough else (0,)):
        problem.n_lens = n_lens
        sol = _robust_solve(problem, state, cfg)
        state = sol.state
    per_view: dict[int, list[np.ndarray]] = {}
    for g, e in zip(groups, sol.errors):
        per_view.setdefault(g.view, []).append(e)
    rms = {i: _rms(e) for i, e in per_view.items()}
    limit = max(cfg.view_outlier_min_px, cfg.view_outlier_factor * float(np.median(list(rms.values()))))
    bad = [i for i, r in rms.items() if r > limit and not (keep_first and i == 0)]
    if bad:
        for i in bad:
            views[i].reason = (f"its corners reproject at {rms[i]:.1f} px while the camera's views reproject at "
                               f"{np.median(list(rms.values())):.2f} px (median): another camera's image, a moved lens "
                               "or a wrongly detected target")
        return _flat_stage(target, views, known, k3, cfg, what, keep_first)
    return state.K[0], state.lens[0], {k: state.shots[s] for s, k in enumerate(keys)}


# ---------------------------------------------------------------- step 3: everything together
def _free_faces(n_faces: int, shot_faces: list[set[int]], rigid: bool) -> np.ndarray:
    """Faces whose pose the shots determine: each face seen together with another face in one
    shot joins that face's group; the lowest face of each group stays at its nominal pose (the
    frame: face 0 for the group holding it), and so does a face never seen with another."""
    parent = list(range(n_faces))

    def root(f: int) -> int:
        while parent[f] != f:
            parent[f] = parent[parent[f]]
            f = parent[f]
        return f

    for faces in shot_faces:
        faces = sorted(faces)
        for f in faces[1:]:
            a, b = root(faces[0]), root(f)
            parent[max(a, b)] = min(a, b)
    free = np.array([root(f) != f for f in range(n_faces)])
    return np.zeros(n_faces, bool) if rigid else free


def _shots(views: list[list[ViewResult]], rig: bool) -> list[list[tuple[int, int]]]:
    """The shots: the views of one moment, [(camera, view index)]. A rig's cameras took their
    i-th views together; otherwise every view is a shot of its own."""
    if rig:
        return [[(c, i) for c in range(len(views)) if views[c][i].used] for i in range(len(views[0]))]
    return [[(c, i)] for c in range(len(views)) for i in range(len(views[c])) if views[c][i].used]


def _joint_problem(target: Target, views: list[list[ViewResult]], flat: list[tuple], rig: bool, rigid: bool,
                   known: list, k3: bool) -> tuple[Problem, State, list[list[tuple[int, int]]]]:
    C, F = len(views), len(target.faces)
    shots = [s for s in _shots(views, rig) if s]
    faces_of = [set().union(*({f for f, _ in _face_groups(views[c][i].detection)} for c, i in s)) for s in shots]
    local = np.array([len(f) == 1 for f in faces_of])
    free_faces = _free_faces(F, [f for f in faces_of if len(f) > 1], rigid)
    # each member view's pose from step 2: its largest face's, which maps that face's nominal points
    start = {}
    for s in shots:
        for c, i in s:
            det = views[c][i].detection
            ranked = sorted(_face_groups(det), key=lambda fg: -len(fg[1]))
            pose = next((flat[c][2][(i, f)] for f, _ in ranked if (i, f) in flat[c][2]), None)
            if pose is not None:
                start[c, i] = pose
    rig_poses = np.zeros((C, 6))
    if rig:
        for c in range(1, C):
            pairs = [rt.compose(start[c, i], rt.inverse(start[0, i])) for i in range(len(views[0]))
                     if (0, i) in start and (c, i) in start]
            if not pairs:
                raise StereoseedError(f"--rig: no shot in which camera 1 and camera {c + 1} both see the target; the "
                                      "rig's relative pose needs at least one")
            rig_poses[c] = rt.mean_pose(pairs)
    shot_poses, groups = [], []
    for s_index, s in enumerate(shots):
        c, i = next(((c, i) for c, i in s if (c, i) in start), s[0])
        shot_poses.append(rt.compose(rt.inverse(rig_poses[c]), start[c, i]))
        for c, i in s:
            det = views[c][i].detection
            for f, idx in _face_groups(det):
                groups.append(_group(c, s_index, f, c * 100000 + i, det, idx))
    problem = Problem(groups, C, F, len(shots), local, free_faces, np.array([k is None for k in known]),
                      np.array([rig and c > 0 for c in range(C)]), 5 if k3 else 4)
    state = State(np.array([fl[0] for fl in flat]), np.array([fl[1] for fl in flat]), rig_poses, np.zeros((F, 6)),
                  np.array(shot_poses))
    return problem, state, shots


def _bic(problem: Problem, sol: Solution) -> float:
    """The Bayesian information criterion of a fit, Gaussian corner errors: n ln(RSS / n) + k ln n
    over the n = 2 N coordinates of the N corners and the k parameters estimated."""
    e = np.concatenate(sol.errors)
    n = 2 * len(e)
    k = (problem.n_shots * 6 + int(problem.free_faces.sum()) * 6 + int(problem.free_rig.sum()) * 6
         + int(problem.free_intrinsics.sum()) * (4 + problem.n_lens))
    return float(n * np.log(max(float(e @ e), 1e-300) / n) + k * np.log(n))


def _fit(problem: Problem, state: State, cfg: CalibrationConfig) -> Solution:
    """The model fitted with the faces at their nominal pose and, where faces could move
    (``problem.free_faces``), with them free; the free fit is kept when its BIC is lower by
    cfg.refine_evidence_bic (else the faces are fixed again in ``problem``). Both start from
    ``state``, which never depends on the nominal geometry's errors (step 2)."""
    free = problem.free_faces.copy()
    problem.free_faces = np.zeros_like(free)
    nominal = _robust_solve(problem, state, cfg)
    if not free.any():
        return nominal
    problem.free_faces = free
    refined = _robust_solve(problem, state, cfg)
    gain = _bic(problem, refined)
    problem.free_faces = np.zeros_like(free)
    gain = _bic(problem, nominal) - gain
    log.debug("target refined: BIC lower by %.1f", gain)
    if gain > cfg.refine_evidence_bic:
        problem.free_faces = free
        return refined
    return nominal


def _view_errors(problem: Problem, sol: Solution) -> dict[int, list[np.ndarray]]:
    out: dict[int, list[np.ndarray]] = {}
    for g, e in zip(problem.groups, sol.errors):
        out.setdefault(g.view, []).append(e)
    return out


def _leave_one_out(problem: Problem, sol: Solution, shots: list, rig: RigResult, cfg: CalibrationConfig) -> None:
    """The rig's pose again without each shot both cameras saw, from the full answer: the
    largest change of the baseline and of the rotation is what one shot more or less is worth."""
    moves_mm, moves_deg = [], []
    R0 = rig.R
    for s, members in enumerate(shots):
        if len({c for c, _ in members}) < 2:
            continue
        rest = Problem([g for g in problem.groups if g.shot != s], problem.n_cameras, problem.n_faces, problem.n_shots,
                       problem.local, problem.free_faces, problem.free_intrinsics, problem.free_rig, problem.n_lens)
        other = solve(rest, sol.state, sol.huber_px, cfg.max_iterations)
        R, t = rt.to_rt(other.state.rig[1])
        moves_mm.append(float(np.linalg.norm(t - rig.t)))
        moves_deg.append(rt.angle_deg(rt.from_rt(R @ R0.T, np.zeros(3))))
    if moves_mm:
        rig.spread_mm, rig.spread_deg = max(moves_mm), max(moves_deg)


def _check_views(views: list[list[ViewResult]], pair: bool, labels: list[str]) -> None:
    """Set aside views of another size or given twice; refuse when the pair's own view is not
    usable (it is the camera the sequence starts from)."""
    for c, cam in enumerate(views):
        size, seen = cam[0].detection.image_size, {}
        for i, v in enumerate(cam):
            if v.used and v.detection.image_size != size:
                w, h = v.detection.image_size
                v.reason = f"{w}x{h} pixels, but {cam[0].name} is {size[0]}x{size[1]}: not this camera's image"
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
    flat = [_flat_stage(target, views[c], known[c], k3, cfg, labels[c], pair) for c in range(C)]
    problem, state, shots = _joint_problem(target, views, flat, rig, rigid_target, known, k3)
    sol = _fit(problem, state, cfg)
    while True:  # views the whole model does not explain are set aside, then it is solved again
        per_view = {k: _rms(e) for k, e in _view_errors(problem, sol).items()}
        median = float(np.median(list(per_view.values())))
        limit = max(cfg.view_outlier_min_px, cfg.view_outlier_factor * median)
        bad = [k for k, r in per_view.items() if r > limit and not (pair and k % 100000 == 0)]
        if not bad:
            break
        for k in bad:
            views[k // 100000][k % 100000].reason = (
                f"its corners reproject at {per_view[k]:.1f} px while the views reproject at {median:.2f} px (median): "
                "another camera's image, a moved lens, or a target that moved between the rig's two exposures")
        problem, state, shots = _joint_problem(target, views, flat, rig, rigid_target, known, k3)
        state.K, state.lens, state.rig = sol.state.K, sol.state.lens, sol.state.rig
        sol = _fit(problem, state, cfg)
    return _results(target, views, problem, sol, shots, rig, rigid_target, known, cfg, labels, leave_one_out)


def _results(target: Target, views: list[list[ViewResult]], problem: Problem, sol: Solution, shots: list, rig: bool,
             rigid: bool, known: list, cfg: CalibrationConfig, labels: list[str], leave_one_out: bool) -> Calibration:
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
                face = int(problem.groups[per_view_groups[c * 100000 + i][0]].face)
                pose = rt.compose(pose, rt.inverse(state.faces[face, :6]))
            v.R, v.t = rt.to_rt(pose)
            det, out = v.detection, np.zeros_like(v.detection.pixels)
            for n in per_view_groups.get(c * 100000 + i, []):
                g = problem.groups[n]
                out[det.face == g.face] = projected[n]
            v.reprojected = out
            err = np.linalg.norm(out - det.pixels, axis=1)
            v.rms_px = float(np.sqrt(np.mean(err * err)))
    cameras, warnings = [], []
    for c, cam in enumerate(views):
        used = [v for v in cam if v.used]
        errors = np.concatenate([np.linalg.norm(v.reprojected - v.detection.pixels, axis=1) for v in used])
        size = cam[0].detection.image_size
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
        if leave_one_out:
            _leave_one_out(problem, sol, shots, rig_result, cfg)
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
    out: dict = {"cameras": [camera_entry(cal, c) for c in range(len(cal.cameras))]}
    out["target_faces"] = [{"face": f, "moved_mm": None if m is None else m[0], "turned_deg": None if m is None else m[1]}
                           for f, m in enumerate(cal.face_moves)]
    if cal.rig is not None:
        out["rig"] = {"R": cal.rig.R.tolist(), "t": cal.rig.t.tolist(), "baseline_mm": cal.rig.baseline_mm,
                      "angle_deg": cal.rig.angle_deg, "shots": cal.rig.shots,
                      "leave_one_out_mm": cal.rig.spread_mm, "leave_one_out_deg": cal.rig.spread_deg}
    if cal.warnings:
        out["warnings"] = cal.warnings
    return out
