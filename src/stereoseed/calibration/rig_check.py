"""A fixed rig's relative pose judged before it is written (:func:`stereoseed.calibration.rig.calibrate_cameras`
runs these on its two fits: each view its own shot, then the rig with each camera's intrinsics held).

With a long lens a camera's principal point and the rig's rotation trade against each other: 85 px
over f = 5000 px is a degree about the other axis, and a joint fit free to move both resolves the
trade by whatever the shots' small inconsistencies favour. So the intrinsics are those each
camera's own views determine, and what is left to judge is:

* the shots against each other (:func:`check_shots`): each shot's relative pose from the two
  cameras' own fits of its views; without a majority agreeing there is no fixed pair that took
  these photos together in this order, and the calibration is refused with that cause;
* the rig's spread (:func:`jackknife`): the one-step jackknife over shots, each camera's
  intrinsics re-estimated without the shot by the fit that determined them and the rig's pose
  following them, so the spread holds the intrinsics' uncertainty, not only the pose's;
* the trade (:func:`refine_target.pulled`): where the shots together would pull each camera's
  intrinsics, their own fit's estimate as a prior, and how far that would turn the rig;
* the pose against the pair's own evidence (:func:`consensus`): the single shots' relative poses
  and the faces' PnP wherever both cameras see one face in one shot.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.calibration import poses as rt
from stereoseed.calibration.config import CalibrationConfig, chi2_quantile_4
from stereoseed.calibration.intrinsics import MIN_HOMOGRAPHY_CORNERS
from stereoseed.calibration.refine_target import Problem, Solution, leave_out, pulled
from stereoseed.calibration.stages import ViewResult, view_of
from stereoseed.errors import StereoseedError

log = logging.getLogger(__name__)

__all__ = ["RigResult", "judge", "view_poses", "shot_poses", "check_shots", "Spread", "jackknife", "consensus",
           "face_pnp_poses"]

# the median 3D error's norm over the RMS of the norm, for a normal error alike on the 3 axes
# (1.538 sigma against sqrt(3) sigma): a robust RMS of scattered estimates from their median
_MEDIAN_TO_RMS_3D = 1.126


@dataclass
class RigResult:
    """Camera c's pose from camera 0's (R, t: X_c = R X_0 + t) and how well the shots determine
    it (:func:`judge`): with one shot left out, each camera's intrinsics re-estimated too, the
    largest change of t (mm) and of the rotation (degrees), and cfg.rig_uncertainty_sigmas
    standard errors of the jackknife; where the shots would pull each camera's intrinsics
    (``trade``); the pose against the pair's own evidence (``checks``)."""
    R: np.ndarray
    t: np.ndarray
    shots: int
    spread_mm: float | None = None
    spread_deg: float | None = None
    uncertainty_mm: float | None = None
    uncertainty_deg: float | None = None
    trade: list[dict] = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.t))

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(cv2.Rodrigues(self.R)[0])))

    def as_json(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist(), "baseline_mm": self.baseline_mm, "angle_deg": self.angle_deg,
                "shots": self.shots, "leave_one_out_mm": self.spread_mm, "leave_one_out_deg": self.spread_deg,
                "uncertainty_mm": self.uncertainty_mm, "uncertainty_deg": self.uncertainty_deg,
                "intrinsics_pull": self.trade, "checks": self.checks}


def view_poses(problem: Problem, sol: Solution, shots: list) -> dict[tuple[int, int], np.ndarray]:
    """Each view's pose (camera from the target's frame, 6-vector) in a solution."""
    out = {}
    for s, members in enumerate(shots):
        for c, i in members:
            pose = rt.compose(sol.state.rig[c], sol.state.shots[s])
            if problem.local[s]:
                face = next(g.face for g in problem.groups if g.shot == s)
                pose = rt.compose(pose, rt.inverse(sol.state.faces[face]))
            out[c, i] = pose
    return out


def shot_poses(problem: Problem, sol: Solution, shots: list, camera: int = 1) -> dict[int, np.ndarray]:
    """Per shot (view index) both cameras saw, camera ``camera``'s pose from camera 0's that the
    two views give, each fitted on its own (a fit where every view is its own shot)."""
    poses = view_poses(problem, sol, shots)
    return {i: rt.compose(poses[camera, i], rt.inverse(poses[0, i])) for c, i in sorted(poses)
            if c == 0 and (camera, i) in poses}


def apart(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """How far two relative poses are: the rotation between them (degrees) and between their
    translations (mm)."""
    return rt.angle_deg(rt.compose(a, rt.inverse(b))), float(np.linalg.norm(a[3:] - b[3:]))


def check_shots(relative: dict[int, np.ndarray], cfg: CalibrationConfig, names: dict[int, tuple[str, str]]
                ) -> list[int]:
    """The shots (view index: its two photos' ``names``) whose relative pose agrees
    (cfg.rig_shot_agreement_deg and _share of the baseline) with the most others'. Raises
    :class:`StereoseedError` when fewer than cfg.rig_min_agreeing_share of them do: the photos
    were not taken together in this order."""
    keys = sorted(relative)
    if len(keys) < 3:  # two shots cannot outvote each other; the rig's fit judges them
        return keys
    baseline = float(np.median([np.linalg.norm(relative[i][3:]) for i in keys]))

    def agree(a: int, b: int) -> bool:
        deg, mm = apart(relative[a], relative[b])
        return deg <= cfg.rig_shot_agreement_deg and mm <= cfg.rig_shot_agreement_share * baseline

    best = max(([b for b in keys if agree(a, b)] for a in keys), key=len)
    if len(best) < cfg.rig_min_agreeing_share * len(keys):
        off = {a: float(np.median([apart(relative[a], relative[b])[0] for b in keys if b != a])) for a in keys}
        worst = max(off, key=off.get)
        raise StereoseedError(
            f"--rig: the shots disagree on camera 2's pose from camera 1: at most {len(best)} of {len(keys)} give it "
            f"within {cfg.rig_shot_agreement_deg:g} deg and {100 * cfg.rig_shot_agreement_share:.0f} % of the baseline "
            f"of each other (a shot typically {float(np.median(list(off.values()))):.0f} deg from the others; "
            f"{names[worst][0]} with {names[worst][1]}: {off[worst]:.0f} deg): the two cameras' photos are not listed in "
            "the same order (the i-th of each taken together), or the cameras moved between shots")
    return best


@dataclass
class Spread:
    """The jackknife over shots of the rig's pose: its standard errors (rotation, degrees, and
    translation, mm) and the largest move one shot left out makes."""
    se_deg: float
    se_mm: float
    max_deg: float
    max_mm: float
    shots: int


def _camera_changes(problem: Problem, sol: Solution, drops: dict, to_camera: list[int], n_cameras: int
                    ) -> dict:
    """Per key of ``drops``, the change of K and of the lens that the fit (problem, sol) makes
    without those corners (the one-step jackknife), for its camera k as camera to_camera[k]."""
    out = {key: (np.zeros((n_cameras, 3, 3)), np.zeros((n_cameras, 5))) for key in drops}
    if not problem.free_intrinsics.any():
        return out
    for key, state in leave_out(problem, sol, drops).items():
        for k, c in enumerate(to_camera):
            if problem.free_intrinsics[k]:
                out[key][0][c] = state.K[k] - sol.state.K[k]
                out[key][1][c] = state.lens[k] - sol.state.lens[k]
    return out


def _intrinsics_without(rig: tuple[Problem, Solution, list], per_camera: tuple[Problem, Solution], flat: list[tuple],
                        from_faces: list[bool], keys: list[int]) -> dict:
    """Per shot (view index), each camera's intrinsics again without it by the fit that gave
    them (the joint fit of every view on its own, or the camera's faces one by one where it keeps
    those: ``from_faces``): their changes (:func:`_camera_changes`)."""
    C = rig[0].n_cameras
    given = _camera_changes(*per_camera, {i: (lambda g, i=i: view_of(g.view)[1] == i) for i in keys},
                            list(range(C)), C)
    for c in range(C):
        if from_faces[c]:  # the flat fit's views are keyed by their index alone (one camera)
            held = _camera_changes(flat[c][5], flat[c][6], {i: (lambda g, i=i: g.view == i) for i in keys}, [c], C)
            for i in keys:
                given[i][0][c], given[i][1][c] = held[i][0][c], held[i][1][c]
    return given


def _spread(rig: tuple[Problem, Solution, list], given: dict) -> Spread:
    """The rig's fit without each shot of ``given``, its cameras' intrinsics moved by the given
    changes: the jackknife's standard errors and largest moves of camera 1's pose from camera 0."""
    problem, sol, _ = rig
    states = leave_out(problem, sol, {i: (lambda g, i=i: view_of(g.view)[1] == i) for i in given}, given)
    ref = sol.state.rig[1]
    turns = np.array([cv2.Rodrigues(rt.to_rt(rt.compose(s.rig[1], rt.inverse(ref)))[0])[0].ravel()
                      for s in states.values()])
    moves = np.array([s.rig[1][3:] - ref[3:] for s in states.values()])
    n = len(states)

    def se(x: np.ndarray) -> float:  # the jackknife's standard error of a vector (its norm)
        return float(np.sqrt((n - 1) / n * np.sum((x - x.mean(axis=0)) ** 2)))

    return Spread(float(np.degrees(se(turns))), se(moves), float(np.degrees(np.linalg.norm(turns, axis=1).max())),
                  float(np.linalg.norm(moves, axis=1).max()), n)


def jackknife(rig: tuple[Problem, Solution, list], per_camera: tuple[Problem, Solution], flat: list[tuple],
              from_faces: list[bool]) -> tuple[Spread, list[Spread], np.ndarray] | None:
    """The rig's pose without each shot both cameras saw, each camera's intrinsics re-estimated
    without it (:func:`_intrinsics_without`) and the rig's fit following them; the same with one
    camera's intrinsics moved at a time (whose intrinsics limit the rig); and each camera's
    principal point's standard errors (C, 2) over the same shots. None with fewer than two
    such shots."""
    keys = sorted({members[0][1] for members in rig[2] if len({c for c, _ in members}) > 1})
    if len(keys) < 2:
        return None
    given = _intrinsics_without(rig, per_camera, flat, from_faces, keys)
    alone = []
    for c in range(rig[0].n_cameras):
        mask = (np.arange(rig[0].n_cameras) == c).astype(float)
        alone.append(_spread(rig, {i: (dK * mask[:, None, None], dl * mask[:, None]) for i, (dK, dl) in given.items()}))
    points = np.array([dK[:, :2, 2] for dK, _ in given.values()])  # (shots, C, 2): cx, cy without each
    n = len(keys)
    return _spread(rig, given), alone, np.sqrt((n - 1) / n * np.sum((points - points.mean(axis=0)) ** 2, axis=0))


def face_pnp_poses(views: list[list[ViewResult]], K: list[np.ndarray], lens: list[np.ndarray]) -> list[np.ndarray]:
    """Per face both cameras saw in one shot (enough corners each for a face's own pose), camera
    2's pose from camera 1's that the face's PnP in each gives: nothing of the target's assembly
    and nothing of the other faces enters it (the views' poses, R and t, are only its start)."""
    out = []
    for v0, v1 in zip(views[0], views[1]):
        if not (v0.used and v1.used):
            continue
        for f in sorted(set(v0.detection.faces_found) & set(v1.detection.faces_found)):
            pose = []
            for c, v in enumerate((v0, v1)):
                m = v.detection.face == f
                if m.sum() < MIN_HOMOGRAPHY_CORNERS:
                    break
                # from the view's pose in the rig's fit: a face alone seen through a long lens has
                # two poses that fit it nearly alike (the planar ambiguity), and the other is wrong
                r0, t0 = cv2.Rodrigues(v.R)[0], v.t.reshape(3, 1).copy()
                ok, r, t = cv2.solvePnP(v.detection.points3d[m], v.detection.pixels[m], K[c], lens[c], r0, t0,
                                        useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
                if not ok or not np.all(np.isfinite(t)):
                    break
                pose.append(np.r_[r.ravel(), t.ravel()])
            if len(pose) == 2:
                out.append(rt.compose(pose[1], rt.inverse(pose[0])))
    return out


def consensus(poses: list[np.ndarray]) -> tuple[np.ndarray, float, float] | None:
    """A robust mean of relative poses (:func:`poses.mean_pose`) and its standard errors
    (rotation degrees, translation mm) from their spread about it (a robust RMS over the square
    root of their number). None for fewer than three."""
    if len(poses) < 3:
        return None
    mean = rt.mean_pose(poses)
    deg, mm = np.array([apart(p, mean) for p in poses]).T
    n = len(poses)
    return mean, float(_MEDIAN_TO_RMS_3D * np.median(deg) / np.sqrt(n)), \
        float(_MEDIAN_TO_RMS_3D * np.median(mm) / np.sqrt(n))


def _weakest(alone: list[Spread], K: list[np.ndarray], point_se: np.ndarray, k: float, labels: list[str]) -> str:
    """The camera whose intrinsics move the rig most when a shot is left out, with its principal
    point and how well its own views determine it (k standard errors over the shots)."""
    c = int(np.argmax([a.se_deg for a in alone]))
    return (f"{labels[c]}'s intrinsics are weakly determined by its views (principal point ({K[c][0, 2]:.0f}, "
            f"{K[c][1, 2]:.0f}) +- ({k * point_se[c, 0]:.0f}, {k * point_se[c, 1]:.0f}) px, f = {K[c][0, 0]:.0f} px; "
            "with a long lens the principal point trades against the rig's rotation): add views with the target near "
            "the frame's edges and corners, tilted")


def judge(result: RigResult, views: list[list[ViewResult]], rig: tuple[Problem, Solution, list],
          per_camera: tuple[Problem, Solution], flat: list[tuple], from_faces: list[bool], covariance: list,
          relative: dict[int, np.ndarray], cfg: CalibrationConfig, labels: list[str], spread: bool = True) -> None:
    """Fill ``result``'s spread, pull and checks from the rig's fit (intrinsics held) and the fit
    of every view on its own (``per_camera``, whose ``relative`` poses per shot are the single
    shots' evidence); its warnings where the rig is weakly determined or disagrees with the
    evidence beyond its stated uncertainty. Raises :class:`StereoseedError` on those with
    cfg.strict."""
    problem, sol, _ = rig
    K = [sol.state.K[c] for c in range(problem.n_cameras)]
    pose = sol.state.rig[1]
    k = cfg.rig_uncertainty_sigmas
    weak = None
    spreads = jackknife(rig, per_camera, flat, from_faces) if spread else None
    se_deg = se_mm = 0.0
    if spread and spreads is None:
        result.warnings.append("rig: fewer than two shots seen by both cameras: nothing tells how well they determine "
                               "camera 2's pose from camera 1; take more shots with both cameras at once")
    if spreads is not None:
        total, alone, point_se = spreads
        se_deg, se_mm = total.se_deg, total.se_mm
        result.spread_mm, result.spread_deg = total.max_mm, total.max_deg
        result.uncertainty_mm, result.uncertainty_deg = k * se_mm, k * se_deg
        weak = _weakest(alone, K, point_se, k, labels)
        if result.uncertainty_deg > cfg.rig_warn_rotation_deg or \
                result.uncertainty_mm > cfg.rig_warn_baseline_share * result.baseline_mm:
            result.warnings.append(
                f"rig: camera 2's pose from camera 1 is determined to +-{result.uncertainty_deg:.2f} deg and "
                f"+-{result.uncertainty_mm:.2f} mm only ({k:g} standard errors over the {total.shots} shots, the "
                f"intrinsics re-estimated with each left out; reliable within {cfg.rig_warn_rotation_deg:g} deg and "
                f"{100 * cfg.rig_warn_baseline_share:g} % of the baseline): {weak}")
    # the principal point/rotation trade: where the shots together would pull the intrinsics
    limit = chi2_quantile_4(cfg.consistency_quantile or 0.999)
    moved = pulled(problem, sol, [None if cov is None else np.linalg.pinv(cov) for cov in covariance])
    turn, shift = apart(moved.rig[1], pose)
    for c, cov in enumerate(covariance):
        if cov is None:
            continue
        d = moved.K[c] - K[c]
        delta = np.array([d[0, 0], d[1, 1], d[0, 2], d[1, 2]])
        result.trade.append({"camera": c, "principal_point_px": [float(moved.K[c][0, 2]), float(moved.K[c][1, 2])],
                             "focal_px": [float(moved.K[c][0, 0]), float(moved.K[c][1, 1])],
                             "chi2": float(delta @ np.linalg.pinv(cov) @ delta), "limit": limit,
                             "rig_turns_deg": turn, "rig_moves_mm": shift})
    most = max(result.trade, key=lambda p: p["chi2"], default=None)
    if most is not None and turn <= (result.uncertainty_deg or 0.0):
        c = most["camera"]
        result.notes.append(
            f"rig: each camera's intrinsics are held at its own views' fit; the shots together would pull {labels[c]}'s "
            f"principal point from ({K[c][0, 2]:.0f}, {K[c][1, 2]:.0f}) to ({most['principal_point_px'][0]:.0f}, "
            f"{most['principal_point_px'][1]:.0f}) px and turn the rig by {turn:.2f} deg, within its stated uncertainty")
    elif most is not None:
        c = most["camera"]
        result.warnings.append(
            f"rig: the shots together pull {labels[c]}'s principal point from ({K[c][0, 2]:.0f}, {K[c][1, 2]:.0f}) to "
            f"({most['principal_point_px'][0]:.0f}, {most['principal_point_px'][1]:.0f}) px (chi-square {most['chi2']:.0f} "
            f"against its own views' fit, 0.999 quantile {limit:.0f}), which would turn the rig by {turn:.2f} deg, more "
            "than its stated uncertainty; kept: each camera's intrinsics as its own views determine them. The shots do "
            "not agree with the cameras' own fits: a target that moved between the two exposures, or "
            + (weak or "weakly determined intrinsics"))
    # the pose against the pair's own evidence, each source with its own standard error
    evidence = {"single_shots": [relative[i] for i in sorted(relative)],
                "faces_pnp": face_pnp_poses(views, K, [sol.state.lens[c] for c in range(problem.n_cameras)])}
    for name, poses in evidence.items():
        found = consensus(poses)
        if found is None:
            continue
        mean, c_deg, c_mm = found
        deg, mm = apart(pose, mean)
        result.checks[name] = {"estimates": len(poses), "rotation_deg": deg, "translation_mm": mm,
                               "their_se_deg": c_deg, "their_se_mm": c_mm}
        if deg > k * np.hypot(se_deg, c_deg) or mm > k * np.hypot(se_mm, c_mm):
            what = "the single shots' relative poses" if name == "single_shots" else "the faces' PnP in both cameras"
            result.warnings.append(
                f"rig: camera 2's pose from camera 1 is {deg:.2f} deg and {mm:.2f} mm from the median of {what} "
                f"({len(poses)}), beyond both's uncertainty ({k:g} standard errors): "
                + (weak or "the shots determine it weakly"))
    log.debug("rig: spread %s, pull %s, checks %s", result.uncertainty_deg, result.trade, result.checks)
    if cfg.strict and result.warnings:
        raise StereoseedError(f"{result.warnings[0]} (refused: --strict)")
