"""Cameras, their lenses, the target's faces and every view's pose estimated together: a sparse
Levenberg-Marquardt on the reprojection error of every detected corner.

A hand-made target is not where its nominal geometry puts it (a face glued 1 mm off, 1 degree
turned): one rigid fit of the nominal geometry then leaves pixels of error that the intrinsics
absorb. As OpenCV's ``calibrateCameraRO`` and pyCamSet do, the geometry is estimated with the
cameras: each face is a rigid body (its printed squares fix the scale) whose pose is a
parameter, face 0 (or the lowest face of each group of faces seen together) fixed as the frame.

The model of a corner X (nominal target coordinates, mm) of face f seen by camera c in shot s::

    x = project_c( T_c o T_s o T_f (X) )

* ``T_f``: the face's pose (6 DOF; identity when fixed). A shot that sees one face only (a flat
  board, a view of one side of a cube) skips it: its pose ``T_s`` is then relative to that
  face's nominal frame, since one face says nothing about where it sits on the target.
* ``T_s``: the shot's pose (camera from target).
* ``T_c``: a stereo rig's relative pose, camera c from the rig's first camera, shared by every
  shot the cameras took together (identity for the first camera, or when the cameras are not a
  rig: every view is then its own shot).
* ``project_c``: camera c's K (fx, fy, cx, cy; zero skew) and lens (k1, k2, p1, p2 [, k3],
  OpenCV's model), :func:`cv2.projectPoints`, which gives the analytic derivatives; the chain
  through the poses is :func:`cv2.composeRT`'s.

Parameters are rotation vectors and translations; the normal equations are summed group by group
(a camera, a shot and a face touch at most 33 parameters) and solved densely (a few hundred
unknowns). The loss is Huber's on each corner's 2D error (iteratively reweighted), the error
measured in that corner's own scale: a corner whose sub-pixel fit failed (a blurred one, left at
OpenCV's position) is worth less than a fitted one (:mod:`stereoseed.calibration.rig`).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.estimators.robust import huber_cost_of_norms, huber_weights

log = logging.getLogger(__name__)

__all__ = ["Group", "Problem", "State", "Solution", "solve", "residuals", "projections", "rotation_vector",
           "intrinsics_covariance", "leave_one_out", "leave_out", "pulled"]


@dataclass
class Group:
    """The corners of one face seen by one camera in one shot."""
    camera: int
    shot: int
    face: int
    view: int  # the image they come from (for per-view statistics)
    points: np.ndarray  # (N, 3) nominal target coordinates
    pixels: np.ndarray  # (N, 2)
    sigma: np.ndarray | None = None  # (N,) each corner's error scale (relative; None: all 1)

    def scale(self) -> np.ndarray:
        return np.ones(len(self.points)) if self.sigma is None else self.sigma


@dataclass
class Problem:
    groups: list[Group]
    n_cameras: int
    n_faces: int
    n_shots: int
    local: np.ndarray  # (n_shots,) bool: the shot's pose is relative to its only face
    free_faces: np.ndarray  # (n_faces,) bool
    free_intrinsics: np.ndarray  # (n_cameras,) bool
    free_rig: np.ndarray  # (n_cameras,) bool: camera c's pose from camera 0 shared by its shots
    n_lens: int = 4  # lens terms estimated: 0 (none), 4 (k1 k2 p1 p2) or 5 (and k3)


@dataclass
class State:
    K: np.ndarray  # (C, 3, 3)
    lens: np.ndarray  # (C, 5)
    rig: np.ndarray  # (C, 6) rotation vector, translation: camera c from camera 0
    faces: np.ndarray  # (F, 6)
    shots: np.ndarray  # (S, 6)

    def copy(self) -> "State":
        return State(self.K.copy(), self.lens.copy(), self.rig.copy(), self.faces.copy(), self.shots.copy())


@dataclass
class Solution:
    state: State
    cost: float
    iterations: int
    converged: bool
    huber_px: float
    errors: list[np.ndarray] = field(default_factory=list)  # per group: (N,) pixel error of each corner


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """The same rotation with an angle below pi: a rotation vector that grew past pi in an update
    is brought back, where its derivatives stay well-behaved."""
    angle = float(np.linalg.norm(r))
    return r * (1.0 - 2.0 * np.pi / angle) if angle > np.pi else r


class _Layout:
    """Where each block of parameters sits in the vector of unknowns."""

    def __init__(self, problem: Problem):
        self.n_intrinsics = 4 + problem.n_lens
        cursor = 0

        def take(free: np.ndarray, size: int) -> list[int | None]:
            nonlocal cursor
            out = []
            for f in free:
                out.append(cursor if f else None)
                cursor += size if f else 0
            return out

        self.camera = take(problem.free_intrinsics, self.n_intrinsics)
        self.rig = take(problem.free_rig, 6)
        self.face = take(problem.free_faces, 6)
        self.shot = take(np.ones(problem.n_shots, bool), 6)
        self.size = cursor

    def apply(self, state: State, dx: np.ndarray, problem: Problem) -> State:
        out = state.copy()
        n = self.n_intrinsics
        for c, i in enumerate(self.camera):
            if i is not None:
                fx, fy, cx, cy = dx[i:i + 4]
                out.K[c] += np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 0.0]])
                out.lens[c, :problem.n_lens] += dx[i + 4:i + n]
        for table, index in ((out.rig, self.rig), (out.faces, self.face), (out.shots, self.shot)):
            for k, i in enumerate(index):
                if i is not None:
                    table[k] += dx[i:i + 6]
                    table[k, :3] = rotation_vector(table[k, :3])
        return out


def _compose(first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """second o first as a 6-vector, and its 6x6 derivatives with respect to first and second."""
    r, t, dr1, dt1_r, dr2, dt2_r, dtr1, dtt1, dtr2, dtt2 = cv2.composeRT(first[:3], first[3:], second[:3], second[3:])
    d_first, d_second = np.empty((6, 6)), np.empty((6, 6))
    d_first[:3, :3], d_first[:3, 3:], d_first[3:, :3], d_first[3:, 3:] = dr1, dt1_r, dtr1, dtt1
    d_second[:3, :3], d_second[:3, 3:], d_second[3:, :3], d_second[3:, 3:] = dr2, dt2_r, dtr2, dtt2
    return np.concatenate([r.ravel(), t.ravel()]), d_first, d_second


def _group_terms(g: Group, problem: Problem, state: State, jacobian: bool
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The group's residuals (2N,) (u, v interleaved) and, if asked, its Jacobian blocks with
    respect to the camera's intrinsics and lens, the rig, the face and the shot pose."""
    apply_face = not problem.local[g.shot]
    pose = state.shots[g.shot]
    d_shot = np.eye(6)
    d_face = None
    if apply_face:
        pose, d_face, d_shot = _compose(state.faces[g.face], pose)
    d_rig = None
    if g.camera and (problem.free_rig[g.camera] or np.any(state.rig[g.camera])):
        pose, d_inner, d_rig = _compose(pose, state.rig[g.camera])
        d_shot = d_inner @ d_shot
        d_face = None if d_face is None else d_inner @ d_face
    proj, J = cv2.projectPoints(g.points, pose[:3], pose[3:], state.K[g.camera], state.lens[g.camera])
    r = (proj.reshape(-1, 2) - g.pixels).ravel()
    if not jacobian:
        return r, {}
    J_pose = J[:, :6]
    blocks = {"shot": J_pose @ d_shot}
    if d_face is not None:
        blocks["face"] = J_pose @ d_face
    if d_rig is not None:
        blocks["rig"] = J_pose @ d_rig
    blocks["camera"] = np.hstack([J[:, 6:10], J[:, 10:10 + problem.n_lens]])
    return r, blocks


def _weights(r: np.ndarray, sigma: np.ndarray, delta: float) -> np.ndarray:
    """IRLS weights per residual: 1 / sigma^2 times Huber's on each corner's 2D error in sigmas,
    repeated for u and v."""
    e = np.hypot(r[0::2], r[1::2]) / sigma
    w = huber_weights(e, delta) / (sigma * sigma)
    return np.repeat(w, 2)


def _cost(problem: Problem, state: State, delta: float) -> float:
    """Huber's cost of the corners' 2D errors, each in its own sigmas."""
    total = 0.0
    for g in problem.groups:
        r, _ = _group_terms(g, problem, state, False)
        e = np.hypot(r[0::2], r[1::2]) / g.scale()
        total += huber_cost_of_norms(e, delta)
    return total if np.isfinite(total) else np.inf


def _normal_equations(problem: Problem, state: State, layout: _Layout, delta: float, parts: list | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """J'WJ and J'Wr summed group by group; each group's (columns, its J'WJ, its J'Wr) appended
    to ``parts`` when given."""
    H = np.zeros((layout.size, layout.size))
    b = np.zeros(layout.size)
    n = layout.n_intrinsics
    for g in problem.groups:
        r, blocks = _group_terms(g, problem, state, True)
        cols, mats = [], []
        for name, start, width in (("camera", layout.camera[g.camera], n), ("rig", layout.rig[g.camera], 6),
                                   ("face", layout.face[g.face], 6), ("shot", layout.shot[g.shot], 6)):
            if start is not None and name in blocks:
                cols.extend(range(start, start + width))
                mats.append(blocks[name])
        if not cols:
            continue
        J = np.hstack(mats)
        w = _weights(r, g.scale(), delta)
        idx = np.asarray(cols)
        Hg, bg = J.T @ (w[:, None] * J), J.T @ (w * r)
        H[np.ix_(idx, idx)] += Hg
        b[idx] += bg
        if parts is not None:
            parts.append((idx, Hg, bg))
    return H, b


def residuals(problem: Problem, state: State) -> list[np.ndarray]:
    """Per group, the (N,) pixel distance between each corner and its projection (not scaled by
    the corners' sigmas)."""
    out = []
    for g in problem.groups:
        r, _ = _group_terms(g, problem, state, False)
        out.append(np.hypot(r[0::2], r[1::2]))
    return out


def projections(problem: Problem, state: State) -> list[np.ndarray]:
    """Per group, the (N, 2) pixels where the model puts its corners."""
    return [g.pixels + _group_terms(g, problem, state, False)[0].reshape(-1, 2) for g in problem.groups]


def solve(problem: Problem, state: State, huber_px: float, max_iterations: int = 100,
          tolerance: float = 1e-8) -> Solution:
    """Levenberg-Marquardt (Marquardt's scaling of the diagonal) from ``state`` on the Huber cost
    with threshold ``huber_px`` (in each corner's sigmas: pixels for a corner of sigma 1).
    Converged when a step lowers the cost by less than ``tolerance`` of it."""
    layout = _Layout(problem)
    cost = _cost(problem, state, huber_px)
    lam, converged, it = 1e-3, False, 0
    for it in range(1, max_iterations + 1):
        H, b = _normal_equations(problem, state, layout, huber_px)
        diag = np.diag(H).copy()
        diag[diag <= 0] = 1.0  # a parameter no residual depends on: keep it where it is
        improved = False
        while lam < 1e12:
            A = H + lam * np.diag(diag)
            try:
                dx = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = layout.apply(state, dx, problem)
            trial_cost = _cost(problem, trial, huber_px)
            if trial_cost < cost:
                decrease = cost - trial_cost
                state, cost = trial, trial_cost
                lam = max(lam / 10, 1e-12)
                improved = True
                converged = decrease <= tolerance * max(cost, 1e-300)
                break
            lam *= 10
        if not improved or converged:
            converged = True
            break
    log.debug("LM: cost %.6g after %d iterations (huber %.3g px)", cost, it, huber_px)
    return Solution(state, cost, it, converged, huber_px, residuals(problem, state))



def intrinsics_covariance(problem: Problem, sol: Solution, camera: int) -> np.ndarray | None:
    """The covariance (4, 4) of camera ``camera``'s fx, fy, cx, cy at the solution: the inverse
    of the normal equations (every other parameter marginalised) scaled by the residuals'
    variance per degree of freedom. None when its intrinsics were not estimated."""
    layout = _Layout(problem)
    start = layout.camera[camera]
    if start is None:
        return None
    H, _ = _normal_equations(problem, sol.state, layout, sol.huber_px)
    n = 2 * sum(len(g.points) for g in problem.groups)
    variance = sol.cost / max(n - layout.size, 1)  # the cost sums squared 2D errors: both coordinates
    diag = np.diag(H).copy()
    H[np.diag_indices_from(H)] = np.where(diag > 0, diag, 1.0)  # parameters no residual touches
    block = slice(start, start + 4)
    return np.linalg.pinv(H)[block, block] * variance


def leave_one_out(problem: Problem, sol: Solution, shots: list[int]) -> dict[int, State]:
    """Per shot of ``shots``, the solution again without its corners: one Gauss-Newton step from
    ``sol`` on the normal equations less that shot's share (the one-step jackknife: exact to
    first order, and a linear solve per shot instead of a fit)."""
    return leave_out(problem, sol, {s: (lambda g, s=s: g.shot == s) for s in shots})


def leave_out(problem: Problem, sol: Solution, drops: dict, given: dict | None = None) -> dict:
    """Per key of ``drops`` (a predicate on the groups to leave out), the one-step jackknife of
    :func:`leave_one_out`. ``given``: per key, the change (C, 3, 3) of K and (C, 5) of the lens
    that another fit found without those corners: the cameras' intrinsics are then moved by it,
    not solved for, and the rest of the parameters follow them (how a two-stage fit, intrinsics
    first and held, answers the same question)."""
    free = problem.free_intrinsics
    if given is not None:  # the camera columns are needed to carry the given change into the rest
        problem.free_intrinsics = np.ones_like(free)
    try:
        layout = _Layout(problem)
        parts: list = []
        H, b = _normal_equations(problem, sol.state, layout, sol.huber_px, parts)
    finally:
        problem.free_intrinsics = free
    camera = np.zeros(layout.size, bool)
    for c, start in enumerate(layout.camera):
        if start is not None:
            camera[start:start + layout.n_intrinsics] = True
    out = {}
    for key, dropped in drops.items():
        Hs, bs = H.copy(), b.copy()
        for g, (idx, Hg, bg) in zip(problem.groups, parts):
            if dropped(g):
                Hs[np.ix_(idx, idx)] -= Hg
                bs[idx] -= bg
        diag = np.diag(Hs).copy()
        Hs[np.diag_indices_from(Hs)] = np.where(diag > 1e-12 * max(diag.max(), 1e-300), diag, 1.0)
        if given is None:
            dx = -np.linalg.solve(Hs, bs)
        else:
            dK, dlens = given[key]
            dx = np.zeros(layout.size)
            for c, start in enumerate(layout.camera):
                dx[start:start + 4] = dK[c, 0, 0], dK[c, 1, 1], dK[c, 0, 2], dK[c, 1, 2]
                dx[start + 4:start + layout.n_intrinsics] = dlens[c, :problem.n_lens]
            rest = ~camera
            dx[rest] = -np.linalg.solve(Hs[np.ix_(rest, rest)], bs[rest] + Hs[np.ix_(rest, camera)] @ dx[camera])
        out[key] = layout.apply(sol.state, dx, problem)
    return out


def pulled(problem: Problem, sol: Solution, information: list[np.ndarray | None]) -> State:
    """One Gauss-Newton step from ``sol`` with each camera's fx, fy, cx, cy free where
    ``information`` gives their prior's information matrix (4, 4), the prior centred on their
    values in ``sol`` (another fit's estimate and its inverse covariance), the lens held: where
    the corners and that fit together put the intrinsics, and every other parameter with them."""
    free = problem.free_intrinsics
    problem.free_intrinsics = np.array([info is not None for info in information])
    try:
        layout = _Layout(problem)
        H, b = _normal_equations(problem, sol.state, layout, sol.huber_px)
    finally:
        problem.free_intrinsics = free
    for start, info in zip(layout.camera, information):
        if start is None:
            continue
        H[start:start + 4, start:start + 4] += info
        lens = slice(start + 4, start + layout.n_intrinsics)  # held: no row couples to it
        H[lens, :], H[:, lens], b[lens] = 0.0, 0.0, 0.0
        H[lens, lens] = np.eye(layout.n_intrinsics - 4)
    diag = np.diag(H).copy()
    H[np.diag_indices_from(H)] = np.where(diag > 0, diag, 1.0)
    return layout.apply(sol.state, -np.linalg.solve(H, b), problem)

