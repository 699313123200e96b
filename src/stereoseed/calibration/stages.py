"""The calibration's two fitting steps (:mod:`stereoseed.calibration.rig` runs them): every face
of every view as a flat board, one camera at a time (:func:`flat_stage`), then everything
together (:func:`joint_problem`, :func:`fit`), with the robust loss's scale and the corners'
error scales measured from the fit itself."""
from __future__ import annotations

import logging
from dataclasses import dataclass


import cv2
import numpy as np

from stereoseed.calibration import poses as rt
from stereoseed.calibration.config import CalibrationConfig
from stereoseed.calibration.detection import MIN_FACE_CORNERS, Detection
from stereoseed.calibration.intrinsics import (MIN_HOMOGRAPHY_CORNERS, face_frame, homography, plane_coordinates,
                                               pose_from_homography, zhang_intrinsics)
from stereoseed.calibration.refine_target import (Group, Problem, State, Solution, intrinsics_covariance, residuals,
                                                  solve)
from stereoseed.calibration.target import Target
from stereoseed.errors import StereoseedError

log = logging.getLogger(__name__)

__all__ = ["ViewResult", "blur_first", "flat_stage", "joint_problem", "fit", "view_errors", "rms", "face_groups", "view_key", "view_of"]


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


def blur_first(view: ViewResult, causes: str) -> str:
    """Why a view reprojects badly: out of focus first where its detection saw blurred faces
    (corners left at OpenCV's position, detection.py), else ``causes``."""
    blurred = sum(view.detection.unrefined)
    if blurred:
        return f"out of focus ({blurred} of its {len(view.detection)} corners blurred: retake it sharp), or {causes}"
    return causes


_VIEWS = 100000  # views per camera the keys leave room for


def view_key(camera: int, index: int) -> int:
    """The key of camera ``camera``'s view ``index`` in Group.view (one number, both recoverable)."""
    return camera * _VIEWS + index


def view_of(key: int) -> tuple[int, int]:
    """(camera, index) of a view's key (:func:`view_key`)."""
    camera, index = divmod(key, _VIEWS)
    return int(camera), int(index)


def _huber(errors: list[np.ndarray], cfg: CalibrationConfig) -> float:
    """Huber's threshold from the corners' errors: a robust sigma of the 2D error (its median
    over 1.1774, the Rayleigh distribution's) times cfg.huber_sigmas, at least huber_min_px."""
    e = np.concatenate(errors) if errors else np.zeros(1)
    return max(cfg.huber_min_px, cfg.huber_sigmas * float(np.median(e)) / 1.1774)


@dataclass
class _Corners(Group):
    refined: np.ndarray | None = None  # (N,) bool: the corner's sub-pixel fit succeeded


def _set_sigmas(problem: Problem, errors: list[np.ndarray] | None, cfg: CalibrationConfig) -> None:
    """Each corner's error scale: 1 for a fitted corner; for one left at OpenCV's position, how
    much larger its errors are (the robust sigmas of the two kinds' errors, both from the same
    fit), so that blurred corners count for what they are worth, on any camera. Too few of
    either kind to measure that: cfg.unrefined_sigma_ratio."""
    ratio = 1.0
    if errors is not None:
        fitted = np.concatenate([e[g.refined] for g, e in zip(problem.groups, errors)])
        other = np.concatenate([e[~g.refined] for g, e in zip(problem.groups, errors)])
        if len(other) >= _MIN_CLASS_CORNERS and len(fitted) >= _MIN_CLASS_CORNERS:
            ratio = max(1.0, float(np.median(other)) / max(float(np.median(fitted)), 1e-12))
        else:
            ratio = cfg.unrefined_sigma_ratio
    for g in problem.groups:
        g.sigma = np.where(g.refined, 1.0, ratio)


# corners of a kind (fitted, or left at OpenCV's position) needed to measure that kind's errors
_MIN_CLASS_CORNERS = 20


def _robust_solve(problem: Problem, state: State, cfg: CalibrationConfig) -> Solution:
    """Solved twice: with every corner alike and Huber's threshold from the start's errors, then
    with each kind of corner at its own scale and the threshold from the first answer's errors."""
    _set_sigmas(problem, None, cfg)
    sol = solve(problem, state, _huber(residuals(problem, state), cfg), cfg.max_iterations)
    _set_sigmas(problem, sol.errors, cfg)
    return solve(problem, sol.state, _huber([e / g.scale() for g, e in zip(problem.groups, sol.errors)], cfg),
                 cfg.max_iterations)


def rms(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.zeros(0)
    return float(np.sqrt(np.mean(e * e))) if len(e) else float("nan")


def _undistorted(pixels: np.ndarray, K: np.ndarray, lens: np.ndarray) -> np.ndarray:
    if not np.any(lens):
        return pixels
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, lens, P=K).reshape(-1, 2)


def _group(camera: int, shot: int, face: int, view: int, det: Detection, idx: np.ndarray) -> "_Corners":
    refined = det.refined[idx] if det.refined is not None else np.ones(len(idx), bool)
    return _Corners(camera, shot, face, view, det.points3d[idx], det.pixels[idx], refined=refined)


def face_groups(det: Detection) -> list[tuple[int, np.ndarray]]:
    """(face, indices of its corners) for each face the view holds enough corners of."""
    return [(f, np.flatnonzero(det.face == f)) for f in np.unique(det.face)
            if np.count_nonzero(det.face == f) >= MIN_FACE_CORNERS]


# ---------------------------------------------------------------- step 2: every face a flat board
def flat_stage(target: Target, views: list[ViewResult], known: tuple | None, k3: bool, cfg: CalibrationConfig,
                what: str, keep_first: bool) -> tuple:
    """One camera's K, lens, per (view, face) the pose that maps the face's nominal points into
    the camera, the covariance of fx, fy, cx, cy (None when given) and the lens terms estimated
    (0 with fewer boards than cfg.min_flat_views: then the joint fit estimates the lens), and the
    fit itself (its problem, each board a shot, and solution: a rig's spread leaves views out of
    it). Views that disagree with the others are marked unused (never the first when
    ``keep_first``: the pair's view, judged by the whole calibration)."""
    size = next(v.detection.image_size for v in views if v.used)
    K = None if known is None else known[0]
    lens = np.zeros(5) if known is None else known[1]
    boards = []  # (view index, face, corner indices, homography or None)
    for i, v in enumerate(views):
        if v.used:
            for f, idx in face_groups(v.detection):
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
    view_rms = {i: rms(e) for i, e in per_view.items()}
    median = float(np.median(list(view_rms.values())))
    limit = max(cfg.view_outlier_min_px, cfg.view_outlier_factor * median)
    bad = [i for i, r in view_rms.items() if r > limit and not (keep_first and i == 0)]
    if bad:
        for i in bad:
            views[i].reason = (f"its corners reproject at {view_rms[i]:.1f} px while the camera's views reproject at "
                               f"{median:.2f} px (median): "
                               + blur_first(views[i], "another camera's image, a moved lens or a wrongly detected target"))
        return flat_stage(target, views, known, k3, cfg, what, keep_first)
    return state.K[0], state.lens[0], {k: state.shots[s] for s, k in enumerate(keys)}, \
        intrinsics_covariance(problem, sol, 0), problem.n_lens, problem, sol


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


def joint_problem(target: Target, views: list[list[ViewResult]], flat: list[tuple], rig: bool, rigid: bool,
                  known: list, k3: bool, prior: tuple[dict, np.ndarray] | None = None
                  ) -> tuple[Problem, State, list[list[tuple[int, int]]]]:
    """The model of step 3 and its start: step 2's intrinsics, and each view's pose from its
    largest face's (step 2), or from ``prior`` = (each view's pose in the target's frame, the
    faces' poses): a rig starts from its cameras' fit as independent views, where one pose per
    view averages over every face it saw."""
    C, F = len(views), len(target.faces)
    shots = [s for s in _shots(views, rig) if s]
    faces_of = [set().union(*({f for f, _ in face_groups(views[c][i].detection)} for c, i in s)) for s in shots]
    local = np.array([len(f) == 1 for f in faces_of])
    free_faces = _free_faces(F, [f for f in faces_of if len(f) > 1], rigid)
    # each member view's pose from step 2: its largest face's, which maps that face's nominal points
    start = {}
    for s in shots:
        for c, i in s:
            det = views[c][i].detection
            ranked = sorted(face_groups(det), key=lambda fg: -len(fg[1]))
            pose = next((flat[c][2][(i, f)] for f, _ in ranked if (i, f) in flat[c][2]), None)
            if pose is not None:
                start[c, i] = pose
    faces = np.zeros((F, 6))
    if prior is not None:
        start, faces = {k: v for k, v in prior[0].items() if k in start}, prior[1].copy()
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
        pose = rt.compose(rt.inverse(rig_poses[c]), start[c, i])
        if prior is not None and local[s_index]:  # a pose in the target's frame, the shot's from its face's
            pose = rt.compose(pose, faces[next(iter(faces_of[s_index]))])
        shot_poses.append(pose)
        for c, i in s:
            det = views[c][i].detection
            for f, idx in face_groups(det):
                groups.append(_group(c, s_index, f, view_key(c, i), det, idx))
    problem = Problem(groups, C, F, len(shots), local, free_faces, np.array([k is None for k in known]),
                      np.array([rig and c > 0 for c in range(C)]), 5 if k3 else 4)
    state = State(np.array([fl[0] for fl in flat]), np.array([fl[1] for fl in flat]), rig_poses, faces,
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


def fit(problem: Problem, state: State, cfg: CalibrationConfig) -> Solution:
    """The model fitted with the faces at their nominal pose and, where faces could move
    (``problem.free_faces``), with them free; the free fit is kept when its BIC is lower by
    cfg.refine_evidence_bic (else the faces are fixed again in ``problem``). Both start from
    ``state`` (the nominal fit with its faces at their nominal pose), which never depends on the
    nominal geometry's errors (step 2)."""
    free = problem.free_faces.copy()
    problem.free_faces = np.zeros_like(free)
    at_nominal = state.copy()
    at_nominal.faces[:] = 0.0  # a start may hold faces found before (a rig's): nominal means nominal
    nominal = _robust_solve(problem, at_nominal, cfg)
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


def view_errors(problem: Problem, sol: Solution) -> dict[int, list[np.ndarray]]:
    out: dict[int, list[np.ndarray]] = {}
    for g, e in zip(problem.groups, sol.errors):
        out.setdefault(g.view, []).append(e)
    return out


