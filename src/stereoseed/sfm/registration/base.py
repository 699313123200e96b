"""Registration of the next image (paper §4.2): its camera from the 3D points it sees.

:func:`register_view` matches I_{k-1} <-> I_k (robust F), chains the matches to the points
I_{k-1} stands for (the paper's B_{k-1}), and resects P_k (robust DLT, then LM under the camera
model). Where that chain is missing or weak, hypotheses from the motion prior compete with it
(:mod:`stereoseed.sfm.motion_prior`); an image turned upside down since the previous one is
matched turned back. It returns a :class:`Registration` or a :class:`RegistrationFailure` and
changes nothing: the mapper commits the result.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Protocol

import cv2
import numpy as np

from stereoseed.geometry.camera import Camera
from stereoseed.geometry.projection import camera_center, depths, project
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import Features
from stereoseed.matching.containers import Matches
from stereoseed.scene.camera_life import HINDSIGHT, WITHDRAWN_FAILURE, Flag, FlagKind
from stereoseed.sfm.motion_prior import (Hypothesis, explained_points, hypotheses_by_motion_prior, recent_points,
                                        trusted_chain_inliers)
from stereoseed.scene.reconstruction import Reconstruction, View, intrinsics_in_frame
from stereoseed.sfm.config import TrustConfig
from stereoseed.sfm.correspondence import CorrespondenceSource, optional
from stereoseed.sfm.registration.settings import RegistrationSettings
from stereoseed.estimators.resection import ResectionResult, implausible_intrinsics, resect
from stereoseed.geometry.models import CameraModel

__all__ = ["FailureKind", "FoundBy", "Registrar", "SparseRegistrar", "Candidate", "Registration", "RegistrationFailure",
           "reported_notes", "register_view", "implausible_motion", "chained_points", "consistent_chain"]



class FailureKind(StrEnum):
    """Why no camera was found, for a program (the report's ``failure``)."""

    IMAGE_SIZE = "image size"  # not the size of the calibrated moving camera's images
    TOO_FEW_MATCHES = "too few matches"  # too few correspondences with reconstructed points
    NO_CAMERA = "no consistent camera"  # the correspondences agree on no plausible camera
    NUMERICAL = "numerical failure"  # a degenerate configuration the checks did not foresee
    DISAGREES = "disagrees with the propagated matches"  # a weak camera the quasi-dense matches refute
    UNREADABLE = "unreadable image"  # the image file cannot be decoded (the run skips it)
    # flagged when placed, then withdrawn: the next image could be placed only without it
    WITHDRAWN = WITHDRAWN_FAILURE
    # the motion prior's camera predicted across views not placed, which nothing confirms
    UNCONFIRMED = "predicted across views not placed, unconfirmed"


class FoundBy(StrEnum):
    """What placed a camera; its value is the report's ``registered_by``."""

    EPIPOLAR_CHAIN = "epipolar chain"  # robust-F matches chained to the previous view's points
    MOTION_PRIOR = "motion prior"  # matches searched where the walk's motion predicts the points
    QUASI_DENSE = "quasi-dense"  # matches propagated from seeds (Lhuillier-Quan), chained
    RIG = "stereo rig"  # both images of a rig's station, their pose resected together (stereoseed.sfm.rig)
    HINDSIGHT = HINDSIGHT  # found again after the final BA, between the views on both sides (sfm.hindsight)




@dataclass(frozen=True)
class Candidate:
    """An image about to be registered, as registration sees it: image ``index`` (its pixels
    ``image``, turned by 180 degrees when ``rotated_180``) and its interest points."""

    index: int
    name: str
    image: np.ndarray
    features: Features
    rotated_180: bool = False

    @property
    def image_size(self) -> tuple[int, int]:
        return self.image.shape[1], self.image.shape[0]

    def in_frame(self, K: np.ndarray, source: View) -> np.ndarray:
        """Intrinsics K (3, 3) of ``source``'s image expressed for this image's frame."""
        return intrinsics_in_frame(K, source.rotated_180, self.rotated_180, self.image_size)


@dataclass(frozen=True)
class Registration:
    """A camera for an image, not yet part of the reconstruction.

    candidate: the image as registered (turned or not) with its interest points; P (3, 4) in
    its frame; resection: the estimate (inliers, RMS, model); found_by: which registrar's
    correspondences placed it; hypothesis: the motion prior's winning hypothesis (None when the
    chain won); free_camera_refused: why the 11-DOF camera was refused (the focal-only model
    took its place), else None; matches, chained_points: of the robust-F matching; seconds:
    time per step."""

    candidate: Candidate
    resection: ResectionResult
    found_by: FoundBy
    matches: int
    chained_points: int
    hypothesis: Hypothesis | None = None
    free_camera_refused: str | None = None
    seconds: dict[str, float] = field(default_factory=dict)  # features, matching, resection
    # found_by "quasi-dense": the propagated matches the commit turns into tracks
    # (:class:`stereoseed.sfm.registration.quasi_dense.QuasiDenseMatches`); the report of the attempt
    quasi_dense: Any = None
    notes: dict[str, Any] = field(default_factory=dict)
    # why the run cannot vouch for the camera (an ambiguous choice), None: it can
    flag: Flag | None = None
    # an ambiguous choice: the rival cameras (3, 4) that explain nearly as much
    rivals: tuple[np.ndarray, ...] = ()

    @property
    def P(self) -> np.ndarray:
        return self.resection.P

    @property
    def camera(self) -> Camera:
        return self.resection.camera

    @property
    def model(self) -> str:
        """The camera model of P: the run's; "fixed" when the previous zoom was kept; "focal"
        (or "fixed") when the run's 11-DOF camera was refused (``free_camera_refused``)."""
        return self.resection.info.get("model")

    @property
    def zoomed(self) -> bool:
        return self.model != CameraModel.FIXED


@dataclass(frozen=True)
class RegistrationFailure:
    """Why an image could not be registered: ``kind`` for a program, ``reason`` (naming the image)
    for a user; ``candidate``: the image as matched, when it got that far (a second attempt can
    start from it)."""

    reason: str
    matches: int = 0
    chained_points: int = 0
    seconds: dict[str, float] = field(default_factory=dict)
    candidate: Candidate | None = None
    notes: dict[str, Any] = field(default_factory=dict)
    kind: FailureKind = FailureKind.NO_CAMERA
    flag: Flag | None = None  # the flag of a camera refused after its registration, as it was


def reported_notes(found: Registration | RegistrationFailure) -> dict[str, Any]:
    """What an outcome's report says besides its figures: its flag's reason ("flag"), then its
    notes."""
    return ({"flag": found.flag.reason} if found.flag is not None else {}) | found.notes


class Registrar(Protocol):
    """One way of placing the next view. ``register`` sees the previous registrar's outcome for
    the view (None for the first): it returns that outcome or a better-founded one, and changes
    nothing in ``recon`` (the mapper commits). The mapper owns the order (:func:`stereoseed.sfm.strategy.registrars`)."""

    def register(self, recon: Reconstruction, source: CorrespondenceSource, k: int,
                 found: Registration | RegistrationFailure | None,
                 settings: RegistrationSettings) -> Registration | RegistrationFailure: ...


class SparseRegistrar:
    """Interest-point matches with the last registered view: the epipolar chain, checked against
    the motion prior's hypotheses (the camera explaining the most recent points wins)."""

    def register(self, recon: Reconstruction, source: CorrespondenceSource, k: int,
                 found: Registration | RegistrationFailure | None,
                 settings: RegistrationSettings) -> Registration | RegistrationFailure:
        try:
            return register_view(recon, k, settings, source)
        except np.linalg.LinAlgError as e:  # a degenerate configuration the checks did not foresee
            return RegistrationFailure(f"{recon.views[k].name}: numerical failure ({e}); skipped",
                                       kind=FailureKind.NUMERICAL)


@dataclass(frozen=True)
class _Failed:
    """No camera from these correspondences: why, for a user and for a program."""

    reason: str
    kind: FailureKind


@dataclass(frozen=True)
class _Resected:
    """A camera from one set of correspondences: the resection, why the 11-DOF camera was refused
    (None: it was not), what found the correspondences, the motion prior's hypothesis (or None),
    and why the run cannot vouch for it (None: it can)."""

    result: ResectionResult
    refused: str | None
    found_by: FoundBy
    hypothesis: Hypothesis | None = None
    flag: Flag | None = None
    rivals: tuple[np.ndarray, ...] = ()  # the cameras (3, 4) that make it ambiguous


def ambiguous_rivals(recon: Reconstruction, prev: int, recent: np.ndarray, cameras: list[np.ndarray], counts: np.ndarray,
            best: int, trust: TrustConfig) -> list[tuple[int, float, float]]:
    """The cameras that make the winner ``best`` of competing cameras (3, 4) ambiguous, as
    (index, distance from the winner, the recent points' depth): each explains at least
    ``TrustConfig.ambiguity_ratio`` of its recent points (``counts``) while its centre stands
    farther than ``ambiguity_shift`` x that depth from it."""
    tc = trust
    if counts[best] == 0:
        return []
    depth = float(np.median(depths(recon.views[prev].P, recon.points[recent]))) if len(recent) else np.inf
    centre = camera_center(cameras[best])
    found = []
    for j, P in enumerate(cameras):
        if j == best or counts[j] < tc.ambiguity_ratio * counts[best]:
            continue
        apart = float(np.linalg.norm(camera_center(P) - centre))
        if apart > tc.ambiguity_shift * depth:
            found.append((j, apart, depth))
    return found


def ambiguity_flag(rivals: list[tuple[int, float, float]], counts: np.ndarray, best: int) -> Flag | None:
    """The flag of a choice :func:`ambiguous_rivals` makes ambiguous (what the first rival explains
    against the winner ``best``), or None without one."""
    if not rivals:
        return None
    j, apart, depth = rivals[0]
    return Flag(FlagKind.AMBIGUOUS, f"(the best camera explains {counts[best]} recent points, another {apart:.3g} "
                                    f"away ({100 * apart / depth:.1f} % of the scene's depth) explains {counts[j]})")


def implausible_motion(P: np.ndarray, previous: View, points: np.ndarray, steps: int, max_zoom: float) -> str | None:
    """Why camera P (3, 4) cannot follow the ``previous`` registered view, or None: its focal
    length changed by more than ``max_zoom`` (either way), or its centre moved farther than
    the median depth of ``points`` (N, 3) in the previous camera, per image ``steps`` since. A
    hand-held zoom and a walk around the object (10-20 degrees, a third of the object's
    distance) do neither; a camera fitted to wrong correspondences (repeated patterns, a
    near-planar set) often does."""
    f = Camera(P).focal
    f_prev = previous.focal
    if not (np.isfinite(f) and f_prev / max_zoom <= f <= f_prev * max_zoom):
        return (f"the estimated camera is implausible (focal length {f:.0f} px after {f_prev:.0f} px in the "
                f"previous image); its matches are probably wrong")
    depth = np.median(depths(previous.P, points)) if len(points) else np.inf
    step = float(np.linalg.norm(camera_center(P) - previous.center))
    if not step <= depth * max(steps, 1):
        return (f"the estimated camera is implausible (it moved {step:.3g} from the previous image, which sees "
                f"the points {depth:.3g} away); its matches are probably wrong")
    return None


def chained_points(recon: Reconstruction, prev: int, m: Matches) -> tuple[np.ndarray, np.ndarray]:
    """(point ids (M,) of prev's matched interest points, chained (M,) bool: a live point)."""
    pid = recon.views[prev].point_of_feature[m.idx1]
    return pid, (pid >= 0) & recon.alive[np.maximum(pid, 0)]


def consistent_chain(recon: Reconstruction, prev: int, k: int, m: Matches,
                     threshold_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For matches prev <-> k once view k's camera is committed: (point ids (M,), chained (M,)
    bool, consistent (M,) bool: chained and k's interest point within ``threshold_px`` of the
    point's projection)."""
    pid, chained = chained_points(recon, prev, m)
    consistent = np.zeros(len(m), bool)
    if chained.any():
        view = recon.views[k]
        err = np.linalg.norm(project(view.P, recon.points[pid[chained]]) - view.features.points[m.idx2[chained]],
                             axis=1)
        consistent[np.flatnonzero(chained)[err <= threshold_px]] = True
    return pid, chained, consistent


class Resector:
    """Resection of one candidate under the run's camera model, each result validated (a
    plausible motion; an 11-DOF camera must be a physical one, else the focal-only model)."""

    def __init__(self, recon: Reconstruction, prev: int, cand: Candidate, settings: RegistrationSettings,
                 may_zoom: bool = True):
        self.settings, self.cand, self.prev = settings, cand, recon.views[prev]
        self.steps = cand.index - prev
        self.model = settings.camera_model
        self.ref_K = cand.in_frame(recon.views[1].K, recon.views[1])
        self.fallback_K = cand.in_frame(self.prev.K, self.prev) if self.model != CameraModel.FREE else None
        # may_zoom False: a "focal" camera keeps the previous image's intrinsics (the "fixed"
        # model on them), for correspondences that cannot tell a zoom from a move (see
        # quasi_dense_registration.register_quasi_dense)
        self.may_zoom = may_zoom

    def _attempt(self, X3: np.ndarray, x2: np.ndarray, scores: np.ndarray, model: str,
                 fallback_K: np.ndarray | None) -> ResectionResult | str:
        name = self.cand.name
        reference_K = self.ref_K
        if model == CameraModel.FOCAL and not self.may_zoom and fallback_K is not None:
            model, reference_K, fallback_K = CameraModel.FIXED, fallback_K, None
        try:
            res = resect(X3, x2, self.settings.resection, scores=scores, image_size=self.cand.image_size, model=model,
                         reference_K=reference_K, what=name, fallback_K=fallback_K)
            why = implausible_motion(res.P, self.prev, X3, self.steps, self.settings.registration.max_zoom_step)
            if not why and model == CameraModel.FREE:
                why = implausible_intrinsics(res.P, self.ref_K, self.cand.image_size, self.settings.resection)
                why = why and f"the 11-DOF camera is ill-conditioned ({why})"
        except StereoseedError as e:
            return str(e)
        except np.linalg.LinAlgError as e:  # a degenerate configuration the checks did not foresee
            return f"{name}: numerical failure of the resection ({e})"
        return f"{name}: {why}" if why else res

    def each(self, hypotheses: list[Hypothesis]) -> tuple[list[tuple[tuple[ResectionResult, str | None], Hypothesis]],
                                                        str | None]:
        """The cameras of the ``hypotheses`` long enough to be resected
        (``RegistrationConfig.min_chained_points``): ([(what :meth:`__call__` found, its hypothesis)],
        the last failure's reason or None)."""
        found, error = [], None
        for hyp in hypotheses:
            if len(hyp) < self.settings.registration.min_chained_points:
                continue
            res = self(hyp.points3d, hyp.points2d, hyp.scores)
            if isinstance(res, str):
                error = res
            else:
                found.append((res, hyp))
        return found, error

    def __call__(self, X3: np.ndarray, x2: np.ndarray, scores: np.ndarray) -> tuple[ResectionResult, str | None] | str:
        """(result, why the 11-DOF camera was refused or None), or the reason of the failure."""
        res = self._attempt(X3, x2, scores, self.model, self.fallback_K)
        if not isinstance(res, str) or self.model != CameraModel.FREE:
            return res if isinstance(res, str) else (res, None)
        # 11 DOF from points on a few faces of a small object far away: the focal length trades
        # against the distance. The calibrated camera's intrinsics with a free zoom (the
        # "focal" model) take the refused camera's place rather than losing the sequence; "no
        # zoom" is the previous focal length on the calibrated principal point and aspect.
        unchanged_zoom = self.ref_K.copy()
        unchanged_zoom[:2, :2] *= self.prev.focal / self.ref_K[0, 0]
        focal = self._attempt(X3, x2, scores, "focal", unchanged_zoom)
        return res if isinstance(focal, str) else (focal, res)


def _turned(source, cand: Candidate) -> Candidate:
    image = cv2.rotate(cand.image, cv2.ROTATE_180)
    return Candidate(cand.index, cand.name, image, source.features(cand.index, image), not cand.rotated_180)


def register_view(recon: Reconstruction, k: int, settings: RegistrationSettings,
                  source: CorrespondenceSource) -> Registration | RegistrationFailure:
    """A camera for view k from the last registered view before it, from the correspondences of
    ``source`` (the mapper's). Changes nothing in ``recon``."""
    prev = recon.registered_before(k, 1)[0]
    vp, view = recon.views[prev], recon.views[k]
    moving = recon.views[1]
    if view.image_size != moving.image_size:
        (w, h), (w1, h1) = view.image_size, moving.image_size
        return RegistrationFailure(f"{view.name}: {w}x{h} pixels, but the calibrated moving camera's images are "
                                   f"{w1}x{h1}; give images of that size (its intrinsics are in pixels of that size)",
                                   kind=FailureKind.IMAGE_SIZE)
    seconds = {}
    t = time.perf_counter()
    cand = Candidate(k, view.name, view.image, source.features(k, view.image), view.rotated_180)
    seconds["features"] = time.perf_counter() - t
    t = time.perf_counter()
    width = vp.image_size[0]
    m = source.match(prev, k, vp.features, cand.features, None, width)
    pid, chained = chained_points(recon, prev, m)
    if chained.sum() < settings.resection.min_inliers and optional(source, "turns_images"):
        # a camera turned upside down since the previous image (a ring walked over the top of
        # an object) matches only once its image is turned back
        turned = _turned(source, cand)
        m2 = source.match(prev, k, vp.features, turned.features, None, width)
        pid2, chained2 = chained_points(recon, prev, m2)
        if chained2.sum() > chained.sum():
            cand, m, pid, chained = turned, m2, pid2, chained2
    seconds["matching"] = time.perf_counter() - t
    t = time.perf_counter()
    found = _resect(recon, prev, cand, recon.points[pid[chained]], cand.features.points[m.idx2[chained]],
                    m.score[chained], settings)
    seconds["resection"] = time.perf_counter() - t
    n_matches, n_chained = len(m), int(chained.sum())
    if isinstance(found, _Failed):
        return RegistrationFailure(found.reason, n_matches, n_chained, seconds, cand, kind=found.kind)
    return Registration(cand, found.result, found.found_by, n_matches, n_chained, found.hypothesis, found.refused,
                        seconds, flag=found.flag, rivals=found.rivals)


def _trusted_chain(inliers: np.ndarray, settings: RegistrationSettings) -> bool:
    """Whether the epipolar chain's camera, with ``inliers`` (N,) bool over its 3D-2D pairs, is
    taken without consulting the motion prior: enough inliers (``trusted_chain_factor`` x a
    resection's), and too few outliers to hold a rival that explains nearly as much
    (``TrustConfig.ambiguity_ratio`` of the inliers): a robust F fitted to a repeated pattern
    matched one period over splits the chain between the copies (the castle walked backwards:
    24 of 43 pairs agreed on a camera 4.7 m off)."""
    n_in = int(inliers.sum())
    return (n_in >= trusted_chain_inliers(settings.motion_prior, settings.resection)
            and len(inliers) - n_in < settings.trust.ambiguity_ratio * n_in)


def _resect(recon: Reconstruction, prev: int, cand: Candidate, X3: np.ndarray, x2: np.ndarray, scores: np.ndarray,
            settings: RegistrationSettings) -> _Resected | _Failed:
    """The camera of ``cand`` from its chained 3D-2D correspondences (points3d (N, 3),
    points2d (N, 2), ZNCC scores (N,)), or the reason there is none.

    A weak chain is checked against the motion prior even at the first insertion, where the
    prediction only extrapolates the stereo pair's baseline (a robust F fitted to period-
    shifted squares can place a camera 18 cm off). The camera explaining the most recent
    points wins; the wide search's camera replaces the near one's only when it explains
    clearly more (more candidates also mean more chances for a slightly worse camera to win
    by a point or two)."""
    mp = settings.motion_prior
    resect_with = Resector(recon, prev, cand, settings)
    chain, error = None, None
    if len(X3) >= settings.resection.min_inliers:
        chain = resect_with(X3, x2, scores)
        if isinstance(chain, str):
            chain, error = None, chain
        prior_exists = bool(recon.registered_before(prev, 1))
        if chain is not None and (not prior_exists or _trusted_chain(chain[0].inliers, settings)):
            return _Resected(*chain, FoundBy.EPIPOLAR_CHAIN)
    recent = recent_points(recon, prev, mp.recent_views)
    chosen, explained, flag, rivals = None, 0, None, ()
    for hypotheses in hypotheses_by_motion_prior(recon, prev, cand.index, cand.features, mp, settings.resection,
                                                  recent):
        # (camera, its hypothesis; None for the epipolar chain's, which competes in the first search)
        cameras = [(chain, None)] if chain is not None and chosen is None else []
        found, failed = resect_with.each(hypotheses)
        cameras += found
        error = failed or error
        if not cameras:
            continue
        counts = explained_points(cand.features, [c[0][0].P for c in cameras], recon.points[recent[0]], recent[1],
                                  mp.explain_px, mp.min_zncc)
        best = int(np.argmax(counts))  # ties: the first (the epipolar chain's, the nearest search's)
        if chosen is None or (counts[best] > 0 and counts[best] >= mp.wider_search_margin * explained):
            chosen, explained = cameras[best], counts[best]
            # a repeated pattern: another camera, a period away, explains nearly as much. The best
            # is kept (the walk goes on from it) but flagged: nothing is vouched for on a margin
            Ps = [c[0][0].P for c in cameras]
            ambiguous = ambiguous_rivals(recon, prev, recent[0], Ps, counts, best, settings.trust)
            flag, rivals = ambiguity_flag(ambiguous, counts, best), tuple(Ps[j] for j, _, _ in ambiguous)
    if chosen is not None:
        found_by = FoundBy.EPIPOLAR_CHAIN if chosen[1] is None else FoundBy.MOTION_PRIOR
        return _Resected(*chosen[0], found_by, chosen[1], flag, rivals)
    if error:
        return _Failed(error, FailureKind.NO_CAMERA)
    # (the chain is resected from ResectionConfig.min_inliers pairs on: fewer say nothing here)
    return _Failed(f"{cand.name}: only {len(X3)} matches with already reconstructed points (need "
                   f"{settings.resection.min_inliers}); the view is too far from {recon.views[prev].name} "
                   f"or too poorly textured", FailureKind.TOO_FEW_MATCHES)
