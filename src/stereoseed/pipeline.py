"""The incremental reconstruction loop (paper §4.1-4.3), one short function per step.

    recon = initialise(images, names, P_pair, cfg)      # match I1-I2, triangulate, filter
    for k in 2 .. n-1: insert_view(recon, k, cfg)       # match, chain, resect, triangulate, local BA
    finish(recon, cfg)                                  # loop closure / final global BA (optional)

``reconstruct`` runs all of it; every step returns a JSON-able report and an insertion that
fails is reported with its reason and skipped: the run keeps what it has.

Beyond the paper (``mode="accurate"``): points are tracked into the new view and the older views
of the window by projection + patch alignment, re-triangulated from their whole track, and the
last W cameras are adjusted together. In both modes, an insertion whose epipolar geometry cannot
be found falls back on a constant-motion prediction of the camera, and a view turned upside down
is matched turned back.
"""
from __future__ import annotations

import time
import warnings
from typing import Any, Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .bundle import BundleProblem, bundle_adjust
from .camera import camera_center, decompose_projection, depths, fundamental_from_projections, project
from .config import Config
from .errors import StereoseedError
from .features import Features, describe, extract_features
from .matching.alignment import PairCache, align_matches, refine_features
from .matching.containers import Matches
from .matching.pair import match_pair
from .matching.two_view import epipolar_band_mask
from .reconstruction import Reconstruction, View
from .resection import implausible_intrinsics, resect
from .triangulation import triangulate, triangulate_tracks

__all__ = ["initialise", "insert_view", "finish", "reconstruct", "adjust"]

Progress = Callable[[int, int, str], None]


def _colors(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """RGB colours (N, 3) uint8 at pixels xy (N, 2) of a BGR image."""
    h, w = image.shape[:2]
    u = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    return image[v, u][:, ::-1] if image.ndim == 3 else np.repeat(image[v, u][:, None], 3, axis=1)


class HarrisZncc:
    """The paper's correspondences: Harris interest points matched by ZNCC under the epipolar
    constraint (known F) or a robust F. Any object with the same two methods can replace it
    (tests use exact correspondences from the synthetic scene to measure the chain alone)."""

    first_look_zncc = 0.3  # unaligned ZNCC a tracked point must reach before it is aligned

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self._pair_caches: list[PairCache] = []

    def _cache(self, fa: Features, fb: Features) -> PairCache:
        """The cache of the pair (fa, fb): an insertion matches its pair up to four times and
        then refines it, over largely the same candidates. The last two pairs only: a cache
        holds both feature sets (with their grey images) and a scores matrix."""
        for c in self._pair_caches:
            if c.covers(fa, fb):
                return c
        self._pair_caches = self._pair_caches[-1:] + [PairCache(fa, fb)]
        return self._pair_caches[-1]

    def features(self, index: int, image: np.ndarray) -> Features:
        return extract_features(image, self.cfg.features, patch_size=self.cfg.matching.patch_size)

    def match(self, a: int, b: int, fa: Features, fb: Features, F: np.ndarray | None, image_width: int) -> Matches:
        mc = self.cfg.matching
        cache = self._cache(fa, fb)
        m = match_pair(fa, fb, mc, F=F, image_width=image_width, cache=cache).matches
        if len(m) < mc.relax_below:
            relaxed = match_pair(fa, fb, mc.relaxed(), F=F, image_width=image_width, cache=cache).matches
            if len(relaxed) > len(m):
                m = relaxed
        return m

    def refine(self, fa: Features, fb: Features, m: Matches) -> Features:
        """fb with its matched points moved onto their partners in a (sub-pixel affine alignment):
        a track followed pair after pair then carries one physical point, not detector noise
        (measured on the box ring: paper-mode drift 4.1 cm -> 0.4 cm)."""
        return refine_features(fa, fb, m, self.cfg.matching, cache=self._cache(fa, fb))

    def track(self, ref: int, target: int, f_ref: Features, ref_idx: np.ndarray, f_target: Features,
              predicted: np.ndarray, max_shift_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Find interest points ``ref_idx`` (K,) of a reference view in a target view, starting at
        their predicted pixels (K, 2): affine alignment of the reference patch (no detector
        involved, so a track survives where Harris does not fire again). Returns (xy (K, 2), ok (K,))."""
        predicted = np.asarray(predicted, np.float64)
        ref_idx = np.asarray(ref_idx, np.int64)
        # cheap first look (unaligned ZNCC at the prediction): occluded points fail it, and
        # the alignment, ~20x dearer, runs only on the rest
        desc, valid = describe(f_target.gray, predicted, f_target.patch_size)
        look = np.flatnonzero(valid & f_ref.valid[ref_idx]
                              & (np.einsum("ij,ij->i", desc, f_ref.desc[ref_idx]) >= self.first_look_zncc))
        xy, ok = predicted.copy(), np.zeros(len(predicted), bool)
        probe = Features(predicted[look], desc[look], valid[look], np.zeros(len(look)), f_target.image_shape, f_target.gray)
        m = Matches(ref_idx[look], np.arange(len(look)), np.ones(len(look)))
        al = align_matches(f_ref, probe, m, self.cfg.matching)
        xy[look] = al.x2
        ok[look] = al.converged & (al.shift(probe, m) <= max_shift_px) & (al.zncc > self.cfg.matching.min_aligned_zncc)
        return xy, ok


def _features(recon: Reconstruction, index: int) -> None:
    view = recon.views[index]
    if view.features is None:
        view.features = recon.source.features(index, view.image)
        view.point_of_feature = np.full(len(view.features), -1, np.int64)


def _match(recon: Reconstruction, a: int, b: int, F: np.ndarray | None = None) -> Matches:
    va, vb = recon.views[a], recon.views[b]
    return recon.source.match(a, b, va.features, vb.features, F, va.image.shape[1])


def _refine(recon: Reconstruction, a: int, b: int, m: Matches) -> None:
    """Move view b's matched features onto their partners in view a, if the source can."""
    refine = getattr(recon.source, "refine", None)
    if refine is not None and len(m):
        recon.views[b].features = refine(recon.views[a].features, recon.views[b].features, m)


def _triangulate_matches(recon: Reconstruction, a: int, b: int, m: Matches, cfg: Config) -> tuple[np.ndarray, Matches]:
    """Triangulate matches between registered views a, b; keep the valid ones. -> (points, matches)."""
    va, vb = recon.views[a], recon.views[b]
    x1, x2 = m.points(va.features, vb.features)
    res = triangulate(np.stack([va.P, vb.P]), np.stack([x1, x2]), iterations=cfg.triangulation.lm_iterations)
    ok = res.valid(cfg.triangulation.max_reprojection_px, cfg.triangulation.min_angle_deg)
    return res.points[ok], m.subset(ok)


def initialise(images: list[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config = Config(),
               source: Any = None) -> tuple[Reconstruction, dict[str, Any]]:
    """Paper §4.1: the calibrated pair. Harris + ZNCC matches under the known epipolar geometry,
    linear + LM triangulation, filtered by reprojection error, cheirality and angle.

    source: where correspondences come from (default :class:`HarrisZncc`)."""
    t0 = time.perf_counter()
    views = [View(name=n, image=img) for n, img in zip(names, images)]
    recon = Reconstruction(views)
    recon.source = source or HarrisZncc(cfg)
    for i in (0, 1):
        views[i].P = np.asarray(P_pair[i], np.float64)
        views[i].status = "calibrated"
        _features(recon, i)
    F = fundamental_from_projections(views[0].P, views[1].P)
    m = _match(recon, 0, 1, F=F)
    _refine(recon, 0, 1, m)
    X, kept = _triangulate_matches(recon, 0, 1, m, cfg)
    if len(X) < cfg.resection.min_inliers:
        raise StereoseedError(f"{names[0]}, {names[1]}: only {len(X)} points triangulated from the calibrated pair "
                              f"({len(m)} matches); check the calibration belongs to these two images")
    ids = recon.add_points(X, _colors(views[0].image, views[0].features.points[kept.idx1]))
    recon.add_observations(0, kept.idx1, ids)
    recon.add_observations(1, kept.idx2, ids)
    return recon, {"image": names[1], "status": "calibrated pair", "matches": len(m), "new_points": len(ids),
                   "seconds": {"total": time.perf_counter() - t0}}


def _previous_registered(recon: Reconstruction, k: int, count: int) -> list[int]:
    return [i for i in range(k - 1, -1, -1) if recon.views[i].registered][:count]


def insert_view(recon: Reconstruction, k: int, cfg: Config = Config()) -> dict[str, Any]:
    """Paper §4.2-4.3: register view k from the last registered view, add its points, local BA.

    Steps: match I_{k-1} <-> I_k (robust F; turned by 180 degrees or by motion prior if that
    fails), chain to the 3D points, resect (robust DLT, LM under the camera model), re-match
    under the new epipolar geometry, triangulate the new points, track (accurate mode), BA.
    Raises :class:`StereoseedError` (the view is left unregistered) when it cannot be placed.
    """
    pc = cfg.pipeline
    timing: dict[str, float] = {}
    t = time.perf_counter()
    view = recon.views[k]
    prev = _previous_registered(recon, k, 1)[0]
    vp = recon.views[prev]
    _features(recon, k)
    timing["features"] = time.perf_counter() - t

    # 1. match I_{k-1} <-> I_k with a robust F (P_k unknown yet)
    t = time.perf_counter()
    m = _match(recon, prev, k)
    timing["matching"] = time.perf_counter() - t
    # 2. chain: interest points of I_{k-1} that stand for a 3D point (the paper's B_{k-1})
    pid = vp.point_of_feature[m.idx1]
    chained = (pid >= 0) & recon.alive[np.maximum(pid, 0)]
    if chained.sum() < cfg.resection.min_inliers and isinstance(recon.source, HarrisZncc):
        # ZNCC is not rotation invariant: a camera turned upside down since the previous image
        # (a ring walked over the top of an object) matches only once its image is turned back
        m, pid, chained = _try_upside_down(recon, prev, k, m, chained)
    report: dict[str, Any] = {"image": view.name, "matches": len(m), "chained_points": int(chained.sum())}
    if view.rotated_180:
        report["rotated_180"] = True
    # 3. resection: robust DLT then LM under the camera model
    t = time.perf_counter()
    res = _resect_view(recon, prev, k, recon.points[pid[chained]], view.features.points[m.idx2[chained]],
                       m.score[chained], cfg, report)
    view.P = res.P
    timing["resection"] = time.perf_counter() - t
    report.update(resection_inliers=int(res.inliers.sum()), resection_rms_px=res.rms_px,
                  resection_model=res.info.get("model"))
    view.camera_model = "focal" if "fallback_from_free" in res.info else None
    view.zoomed = res.info.get("model") != "fixed"
    if view.camera_model:
        report["free_camera_refused"] = res.info["fallback_from_free"]

    # 4. re-match under the now-known epipolar geometry, then chain and triangulate
    t = time.perf_counter()
    m = _match(recon, prev, k, F=fundamental_from_projections(vp.P, view.P))
    _refine(recon, prev, k, m)
    pid = vp.point_of_feature[m.idx1]
    chained = (pid >= 0) & recon.alive[np.maximum(pid, 0)]
    if chained.any():
        # keep only chained observations consistent with the camera just estimated
        err = np.linalg.norm(project(view.P, recon.points[pid[chained]]) - view.features.points[m.idx2[chained]], axis=1)
        good = np.zeros(len(m), bool)
        good[np.flatnonzero(chained)[err <= cfg.resection.ransac_threshold_px]] = True
    else:
        good = chained
    chain_feats, chain_pids = m.idx2[good], pid[good]
    if pc.mode == "paper":
        # The paper: every match of A_{k-1,k} gives a new 2-view point (S_{k-1,k}); the chained old
        # points enter the cost through their observation in I_k (paper.md §4 trap) but their
        # features keep standing for the new points, which the next insertion chains through.
        recon.add_observations(k, chain_feats, chain_pids, link=False)
        new_m = m
    else:
        recon.add_observations(k, chain_feats, chain_pids)
        new_m = m.subset(~chained & (view.point_of_feature[m.idx2] < 0))
    X, kept = _triangulate_matches(recon, prev, k, new_m, cfg)
    ids = recon.add_points(X, _colors(view.image, view.features.points[kept.idx2]))
    recon.add_observations(prev, kept.idx1, ids, link=pc.mode != "paper")
    recon.add_observations(k, kept.idx2, ids)
    if "motion_prior_correspondences" in report:
        # repeated patterns defeated two-view matching: let a third view decide
        before = _previous_registered(recon, prev, 1)
        if before:
            more = _new_points_three_view(recon, prev, k, before[0], cfg)
            ids = np.concatenate([ids, more])
            report["three_view_points"] = int(len(more))
    grown = chain_pids
    if pc.mode != "paper":
        older = _previous_registered(recon, k, pc.resolved_window() + 1)
        tracked = _track_by_projection(recon, k, older, cfg)
        for j in older:  # the new points of k, searched in the older views of the window
            tracked = np.concatenate([tracked, _track_by_projection(recon, j, [k], cfg)])
        grown = np.concatenate([chain_pids, tracked])
        report["tracked_observations"] = int(len(tracked))
    if pc.mode != "paper" and pc.retriangulate and len(grown):
        _retriangulate(recon, np.unique(grown), cfg)
    timing["triangulation"] = time.perf_counter() - t
    report.update(matches_guided=len(m), chained_observations=int(len(chain_pids)), new_points=int(len(ids)))

    # 5. local bundle adjustment
    t = time.perf_counter()
    if pc.resolved_ba() == "global":
        ba = adjust(recon, cfg, free_views=[i for i in recon.registered_views if i > 1])
    elif pc.mode == "paper":
        window_views = [k] + _previous_registered(recon, k, 2)
        P_resected, X_new = view.P.copy(), recon.points[ids].copy()
        ba = adjust(recon, cfg, free_views=[k], free_points=ids, views_in_cost=window_views)
        try:
            # with few chained points the new camera and its two-view points can slide together
            # (measured on the plain box: 9 chained observations, the camera 680 m away after BA)
            # (the intrinsics bounds are not applied again here: measured on the plain box, an
            # adjusted camera just past them was still better than its resection)
            _check_camera(view.P, vp.P, view.name, recon.points[chain_pids], steps=k - prev)
        except StereoseedError as e:
            view.P, recon.points[ids] = P_resected, X_new
            ba["refused"] = str(e)
    else:
        ba = adjust(recon, cfg, free_views=[i for i in _last_registered(recon, pc.resolved_window()) if i > 1])
    timing["bundle"] = time.perf_counter() - t
    removed = _drop_outliers(recon, cfg)
    view.status = "registered"
    report.update(ba=ba, removed_observations=removed, seconds=timing)
    report["seconds"]["total"] = float(sum(timing.values()))
    return report


# a camera from the wider motion-prior search must explain this many times the points of the
# nearer one's to replace it (a period-shifted camera explains about as many; measured winners: 1.4-1.5x)
_WIDER_SEARCH_MARGIN = 1.2


def _resect_view(recon: Reconstruction, prev: int, k: int, X3: np.ndarray, x2: np.ndarray, scores: np.ndarray,
                 cfg: Config, report: dict[str, Any]) -> Any:
    """Camera of view k from its chained 3D-2D correspondences (points3d (N, 3), points2d (N, 2),
    ZNCC scores (N,)): robust DLT then LM under the camera model. When the chain is missing or
    weak, hypotheses from the motion prior compete with it (:func:`_explained_points`); the
    report gets "motion_prior_correspondences" when one of them wins. Returns the
    :class:`~stereoseed.resection.ResectionResult`; raises :class:`StereoseedError`."""
    pc = cfg.pipeline
    view, vp = recon.views[k], recon.views[prev]
    model = pc.resolved_model()
    ref_K = _reference_K(recon, k)
    fallback_K = _in_frame_of(decompose_projection(vp.P)[0], vp, view) if model != "free" else None

    def resect_as(X3: np.ndarray, x2: np.ndarray, scores: np.ndarray, model: str, fallback_K: np.ndarray | None) -> Any:
        res = resect(X3, x2, cfg.resection, scores=scores, image_size=view.image.shape[1::-1],
                     model=model, reference_K=ref_K, what=view.name, fallback_K=fallback_K)
        _check_camera(res.P, vp.P, view.name, X3, steps=k - prev)
        if model == "free":
            why = implausible_intrinsics(res.P, ref_K, view.image.shape[1::-1], cfg.resection)
            if why:
                raise StereoseedError(f"{view.name}: the 11-DOF camera is ill-conditioned ({why})")
        return res

    def resect_view(X3: np.ndarray, x2: np.ndarray, scores: np.ndarray) -> Any:
        try:
            return resect_as(X3, x2, scores, model, fallback_K)
        except StereoseedError as free_error:
            if model != "free":
                raise
            # 11 DOF from points on a few faces of a small object far away: the focal length
            # trades against the distance (measured on the plain box: 68 correct pairs, the
            # best 11-DOF camera 76 cm off with a third of the true focal length, 0.28 px RMS).
            # Such a camera is refused; the calibrated camera's intrinsics with a free zoom
            # (the "focal" model) take its place rather than losing the rest of the sequence.
            try:
                # "no zoom" means the previous focal length on the calibrated camera's principal
                # point and aspect (the previous 11-DOF K may carry its own ill-conditioning)
                unchanged_zoom = ref_K.copy()
                unchanged_zoom[:2, :2] *= _focal(vp.P) / ref_K[0, 0]
                res = resect_as(X3, x2, scores, "focal", unchanged_zoom)
            except StereoseedError:
                raise free_error from None
            res.info["fallback_from_free"] = str(free_error)
            return res

    res, error = None, None
    if len(X3) >= cfg.resection.min_inliers:
        try:
            res = resect_view(X3, x2, scores)
        except StereoseedError as e:
            error = e
        # A weak chain is checked against the motion prior, even at the first insertion, where
        # the prediction only extrapolates the stereo pair's baseline (the wider search covers
        # the walk): on the plain box a robust F fitted to 23 period-shifted matches placed the
        # first insertion 18 cm off, and everything after it followed. Without a view before
        # ``prev`` there is no motion to extrapolate.
        prior_exists = bool(_previous_registered(recon, prev, 1))
        if res is not None and (not prior_exists or res.inliers.sum() >= 2 * cfg.resection.min_inliers):
            return res
    # No epipolar chain (repeated patterns, little texture), or a weak one: on repeated patterns
    # the robust F may be the pattern shifted by one period (measured on the plain box: 19
    # chained points, a camera 17 cm off). Predict the camera from the previous motion, match
    # the recent points by projection, and let the camera that explains the most points decide.
    recent = _recent_points(recon, prev)
    # The prediction misses by more where the motion changed (the first step after the stereo
    # pair, a skipped image, a camera already off): the correct pairings may lie only in a
    # wider search (measured on the noisy plain box: the prediction 55 px off, the narrow search
    # found only shifted squares). Its cameras replace the nearer ones only when they explain
    # clearly more points: more candidates also mean more chances for a slightly worse camera
    # to win by a point or two (measured on templeSparseRing: 42 vs 38 points, 19 vs 10 mm).
    chosen, explained = None, 0
    # two-view points (paper mode) are known less well than tracked ones and their projections
    # scatter more (plain box, paper mode: all 14 images registered in 10 of 10 renderings when
    # explaining within 3 px, in 9 within 1.5 px)
    explain_px = 3.0 if pc.mode == "paper" else 1.5
    for hypotheses in _correspondences_by_motion_prior(recon, prev, k, cfg, recent, radius_fractions=(0.08, 0.16)):
        cameras, sizes = ([res], [0]) if res is not None and chosen is None else ([], [])
        for hyp in hypotheses:
            if len(hyp[0]) < pc.min_chained_points:
                continue
            try:
                cameras.append(resect_view(*hyp))
                sizes.append(len(hyp[0]))
            except (StereoseedError, np.linalg.LinAlgError) as e:
                error = e
        if not cameras:
            continue
        counts = _explained_points(recon, k, [c.P for c in cameras], recent, max_px=explain_px)
        best = int(np.argmax(counts))  # ties: the first (the epipolar chain's, the nearest search's)
        if chosen is None or (counts[best] > 0 and counts[best] >= _WIDER_SEARCH_MARGIN * explained):
            chosen, explained, chosen_size = cameras[best], counts[best], sizes[best]
    if chosen is not None:
        if chosen_size:
            report["motion_prior_correspondences"] = chosen_size
        return chosen
    report["motion_prior_correspondences"] = 0
    raise error or StereoseedError(
        f"{view.name}: only {len(X3)} matches with already reconstructed points (need {pc.min_chained_points}); "
        f"the view is too far from {vp.name} or too poorly textured")


def _in_frame_of(K: np.ndarray, source: View, target: View) -> np.ndarray:
    """Intrinsics K (3, 3) of ``source``'s image expressed for ``target``'s: turning an image by
    180 degrees maps pixel (x, y) to (W - 1 - x, H - 1 - y), which moves the principal point
    (focal lengths and skew stay, the roll goes into R)."""
    if source.rotated_180 == target.rotated_180:
        return K
    h, w = target.image.shape[:2]
    K = K.copy()
    K[0, 2], K[1, 2] = w - 1 - K[0, 2], h - 1 - K[1, 2]
    return K


def _reference_K(recon: Reconstruction, v: int) -> np.ndarray:
    """The calibrated second camera's K, the reference of the constrained camera models, in view
    v's image frame (measured on templeSparseRing: the views turned by 180 degrees had 1.2-1.4
    degrees of rotation error while their principal point stayed where the unturned image has it)."""
    return _in_frame_of(decompose_projection(recon.views[1].P)[0], recon.views[1], recon.views[v])


def _try_upside_down(recon: Reconstruction, prev: int, k: int, m: Matches, chained: np.ndarray
                     ) -> tuple[Matches, np.ndarray, np.ndarray]:
    """Match view k turned by 180 degrees against ``prev``; keep whichever orientation chains
    more reconstructed points. Returns (matches, point ids of prev's matched features, chained)."""
    view, vp = recon.views[k], recon.views[prev]
    kept = (view.image, view.features, view.point_of_feature, view.rotated_180)
    view.image = cv2.rotate(view.image, cv2.ROTATE_180)
    view.features = None
    view.rotated_180 = not view.rotated_180
    _features(recon, k)
    m2 = _match(recon, prev, k)
    pid2 = vp.point_of_feature[m2.idx1]
    chained2 = (pid2 >= 0) & recon.alive[np.maximum(pid2, 0)]
    if chained2.sum() > chained.sum():
        return m2, pid2, chained2
    view.image, view.features, view.point_of_feature, view.rotated_180 = kept
    return m, vp.point_of_feature[m.idx1], chained


def _focal(P: np.ndarray) -> float:
    """Focal length (px, along x) of camera P (3, 4)."""
    return float(decompose_projection(P)[0][0, 0])


def _check_camera(P: np.ndarray, P_prev: np.ndarray, name: str, points: np.ndarray, steps: int = 1,
                  max_zoom: float = 1.5) -> None:
    """Refuse an implausible resected camera: its focal length jumped by more than ``max_zoom``
    (either way) from the previous image's, or its centre moved farther than the median depth
    of ``points`` (N, 3) (the 3D points it was resected from) in the previous camera, per image
    ``steps`` since. A hand-held zoom and a walk around the object (10-20 degrees, a third of
    the object's distance) do neither; a camera fitted to wrong correspondences (repeated
    patterns, a near-planar set) often does (measured on a plain-box rendering: 2 m off)."""
    f, f_prev = _focal(P), _focal(P_prev)
    if not (np.isfinite(f) and f_prev / max_zoom <= f <= f_prev * max_zoom):
        raise StereoseedError(f"{name}: the estimated camera is implausible (focal length {f:.0f} px after "
                              f"{f_prev:.0f} px in the previous image); its matches are probably wrong")
    depth = np.median(depths(P_prev, points)) if len(points) else np.inf
    step = float(np.linalg.norm(camera_center(P) - camera_center(P_prev)))
    if not step <= depth * max(steps, 1):
        raise StereoseedError(f"{name}: the estimated camera is implausible (it moved {step:.3g} from the previous "
                              f"image, which sees the points {depth:.3g} away); its matches are probably wrong")


def predict_camera(P_before: np.ndarray, P_last: np.ndarray, steps: int = 1) -> np.ndarray:
    """Constant-motion prediction of a later camera: the rigid motion from ``P_before`` to
    ``P_last`` (both (3, 4)) applied ``steps`` more times to ``P_last``, with ``P_last``'s
    intrinsics. -> (3, 4)."""
    def pose(P):
        K, R, t = decompose_projection(P)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return K, T
    _, T_before = pose(P_before)
    K, T_last = pose(P_last)
    T_next = T_last
    for _ in range(max(1, steps)):
        T_next = T_last @ np.linalg.inv(T_before) @ T_next
    return K @ T_next[:3]


def _correspondences_by_motion_prior(recon: Reconstruction, prev: int, k: int, cfg: Config,
                                     recent: tuple[np.ndarray, np.ndarray],
                                     radius_fractions: tuple[float, ...] = (0.08,), min_zncc: float = 0.7,
                                     per_point: tuple[int, ...] = (3, 6), n_hypotheses: int = 3
                                     ) -> list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """3D-2D correspondences for view k without epipolar geometry: the points seen in the last
    registered views are projected with the predicted camera (:func:`predict_camera`); every
    interest point of k within a radius (a fraction of the image width, for each of
    ``radius_fractions``) whose patch matches (ZNCC >= ``min_zncc``, the best few) is a pairing,
    and a robust 2D similarity between predicted and found positions keeps the consistent ones
    (the resection's RANSAC follows).

    A repeated pattern offers several consistent similarities (the prediction shifted by one
    period of the pattern), so up to ``n_hypotheses`` are returned, found one after another
    on the pairings the previous ones left, best supported first; :func:`_explained_points`
    decides between them. On a repeated pattern the true pairing of a point may rank anywhere
    among equally good patches, so the hypotheses are drawn twice: from the best 3 and from the
    best 6 pairings per point (``per_point``). Measured on the plain box, ten renderings: with 3
    only, one image 11 cm off (no hypothesis within 8 cm); with 6 only, two renderings lost
    (more pairings, more shifted similarities first); both: every image within 2.6 cm. Each
    hypothesis is (points3d (N, 3), points2d (N, 2), scores (N,)). ``recent``: the points to
    project and their patches, from :func:`_recent_points`. Returns one list of hypotheses per
    radius (the prediction and the patch scores are computed once for all).
    """
    none: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in radius_fractions]
    before = _previous_registered(recon, prev, 1)
    if not before:
        return none
    vp, vk = recon.views[prev], recon.views[k]
    # images skipped since (failed insertions) count as steps of the same motion
    steps = max(1, round((k - prev) / max(prev - before[0], 1)))
    P_pred = predict_camera(recon.views[before[0]].P, vp.P, steps)
    pids, desc = recent
    if len(pids) < 4 or len(vk.features) == 0:
        return none
    pred = project(P_pred, recon.points[pids])
    width = vk.features.image_shape[1]
    d = np.linalg.norm(pred[:, None, :] - vk.features.points[None, :, :], axis=2)
    zncc_all = desc @ vk.features.desc.T
    zncc_all[:, ~vk.features.valid] = -np.inf
    out = []
    for radius_fraction in radius_fractions:
        zncc = np.where(d > radius_fraction * width, -np.inf, zncc_all)
        ranked = np.argsort(-zncc, axis=1)
        hypotheses = []
        for depth in per_point:
            rows = np.repeat(np.arange(len(pids)), min(depth, ranked.shape[1]))
            cols = ranked[:, :depth].ravel()
            ok = zncc[rows, cols] >= min_zncc
            rows, cols = rows[ok], cols[ok]
            # The prediction misses mostly by a zoom about the principal point and a shift (a
            # changed focal length, a different step): a 4-DOF similarity fitted robustly to the
            # pairings (2-point samples, so a low inlier ratio is fine) says which are consistent.
            cv2.setRNGSeed(int(cfg.resection.seed))
            found = 0
            while len(rows) >= 6 and found < n_hypotheses:
                x = vk.features.points[cols]
                S, inl = cv2.estimateAffinePartial2D(pred[rows], x, method=cv2.RANSAC,
                                                     ransacReprojThreshold=0.015 * width, maxIters=5000,
                                                     confidence=cfg.resection.ransac_confidence)
                if S is None or inl is None or inl.sum() < 6:
                    break
                inl = np.flatnonzero(inl.ravel())
                err = np.linalg.norm(pred[rows[inl]] @ S[:, :2].T + S[:, 2] - x[inl], axis=1)
                order = inl[np.argsort(err)]
                _, first = np.unique(rows[order], return_index=True)
                sel = order[first]
                hypotheses.append((recon.points[pids[rows[sel]]], x[sel], zncc[rows[sel], cols[sel]]))
                found += 1
                rest = np.ones(len(rows), bool)
                rest[inl] = False
                rows, cols = rows[rest], cols[rest]
        out.append(hypotheses)
    return out


def _recent_points(recon: Reconstruction, prev: int) -> tuple[np.ndarray, np.ndarray]:
    """Live points seen in the last three registered views up to ``prev``, each described by
    its patch in the latest of them: (point ids (N,), descriptors (N, D) float32)."""
    recent = [prev] + _previous_registered(recon, prev, 2)
    sel = np.isin(recon.obs_view, recent) & recon.alive[recon.obs_point]
    order = np.flatnonzero(sel)[np.argsort(-recon.obs_view[sel], kind="stable")]
    pids, first = np.unique(recon.obs_point[order], return_index=True)
    obs = order[first]
    desc = np.zeros((len(obs), recon.views[prev].features.desc.shape[1]), np.float32)
    for v in np.unique(recon.obs_view[obs]):
        here = recon.obs_view[obs] == v
        desc[here] = recon.views[v].features.desc[recon.obs_feature[obs[here]]]
    return pids, desc


def _explained_points(recon: Reconstruction, k: int, cameras: list[np.ndarray],
                      recent: tuple[np.ndarray, np.ndarray], max_px: float = 1.5, min_zncc: float = 0.7) -> np.ndarray:
    """How many of the recent points (``recent`` from :func:`_recent_points`) each camera (3, 4)
    for view k explains: a point counts when an interest point of k within ``max_px`` of its
    projection matches its patch (ZNCC >= ``min_zncc``). A camera shifted by one period of a
    repeated pattern explains its own correspondences as well as the true one, but loses the
    points at the pattern's ends and everything else in view. Within 1.5 px rather than 3: a
    camera a few centimetres off still lands most projections within 3 px of some match
    (measured on templeSparseRing: 38 vs 35 points at 3 px chose a camera 19 cm off over a
    1 mm one; at 1.5 px 30 vs 31). -> (len(cameras),) int."""
    vk = recon.views[k]
    pids, desc = recent
    tree = cKDTree(vk.features.points)
    counts = np.zeros(len(cameras), np.int64)
    for i, P in enumerate(cameras):
        with np.errstate(invalid="ignore", divide="ignore"):
            x = project(P, recon.points[pids])
        seen = np.flatnonzero(np.all(np.isfinite(x), axis=1))
        dist, nearest = tree.query(x[seen], distance_upper_bound=max_px)
        close = np.isfinite(dist)
        zncc = np.einsum("nd,nd->n", desc[seen[close]], vk.features.desc[nearest[close]])
        counts[i] = int(np.sum(zncc >= min_zncc))
    return counts


def _new_points_three_view(recon: Reconstruction, a: int, b: int, c: int, cfg: Config,
                           min_zncc: float = 0.7, max_px: float = 1.5) -> np.ndarray:
    """New points from the interest points of views a, b that stand for none yet, when ZNCC
    cannot choose between repeated patterns: every pair within the epipolar band with ZNCC >=
    ``min_zncc`` is triangulated, and kept when a third registered view c has an interest point
    within ``max_px`` of its projection whose patch matches too; each interest point is used
    once (best score first). Returns the new point ids (observed in a, b and c)."""
    va, vb, vc = recon.views[a], recon.views[b], recon.views[c]
    fa = np.flatnonzero((va.point_of_feature < 0) & va.features.valid)
    fb = np.flatnonzero((vb.point_of_feature < 0) & vb.features.valid)
    fc = np.flatnonzero(vc.features.valid)
    if min(len(fa), len(fb), len(fc)) == 0:
        return np.zeros(0, np.int64)
    band = epipolar_band_mask(fundamental_from_projections(va.P, vb.P), va.features.points[fa],
                               vb.features.points[fb], cfg.matching.epipolar_band_px)
    zab = va.features.desc[fa] @ vb.features.desc[fb].T
    ia, ib = np.nonzero(band & (zab >= min_zncc))
    if len(ia) == 0:
        return np.zeros(0, np.int64)
    ia, ib = fa[ia], fb[ib]
    res = triangulate(np.stack([va.P, vb.P]), np.stack([va.features.points[ia], vb.features.points[ib]]),
                      iterations=cfg.triangulation.lm_iterations)
    ok = res.valid(cfg.triangulation.max_reprojection_px, cfg.triangulation.min_angle_deg)
    ia, ib, X = ia[ok], ib[ok], res.points[ok]
    if len(ia) == 0:
        return np.zeros(0, np.int64)
    dist, nearest = cKDTree(vc.features.points[fc]).query(project(vc.P, X))
    ic = fc[np.minimum(nearest, len(fc) - 1)]
    score = np.minimum(np.einsum("ij,ij->i", va.features.desc[ia], vc.features.desc[ic]),
                       np.einsum("ij,ij->i", va.features.desc[ia], vb.features.desc[ib]))
    ok = (dist <= max_px) & (score >= min_zncc)
    order = np.flatnonzero(ok)[np.argsort(-score[ok])]
    used_a, used_b, used_c, keep = set(), set(), set(), []
    for o in order:  # greedy one-to-one, best first (a few hundred candidates at most)
        if ia[o] in used_a or ib[o] in used_b or ic[o] in used_c:
            continue
        used_a.add(ia[o]); used_b.add(ib[o]); used_c.add(ic[o]); keep.append(o)
    keep = np.array(keep, np.int64)
    if len(keep) == 0:
        return np.zeros(0, np.int64)
    c_free = vc.point_of_feature[ic[keep]] < 0
    keep = keep[c_free]
    ids = recon.add_points(X[keep], _colors(vb.image, vb.features.points[ib[keep]]))
    recon.add_observations(a, ia[keep], ids)
    recon.add_observations(b, ib[keep], ids)
    recon.add_observations(c, ic[keep], ids)
    return ids


def _append_features(recon: Reconstruction, v: int, xy: np.ndarray) -> np.ndarray:
    """Add interest points at pixels xy (K, 2) to view v (found by tracking, not detection);
    returns their feature indices (K,)."""
    view = recon.views[v]
    f = view.features
    if f.gray is not None:
        desc, valid = describe(f.gray, xy, f.patch_size)
    else:
        desc, valid = np.zeros((len(xy), f.desc.shape[1]), np.float32), np.ones(len(xy), bool)
    start = len(f)
    view.features = Features(np.vstack([f.points, xy]), np.vstack([f.desc, desc]), np.concatenate([f.valid, valid]),
                             np.concatenate([f.response, np.zeros(len(xy))]), f.image_shape, f.gray)
    view.point_of_feature = np.concatenate([view.point_of_feature, np.full(len(xy), -1, np.int64)])
    return np.arange(start, start + len(xy))


def _track_by_projection(recon: Reconstruction, target: int, refs: list[int], cfg: Config) -> np.ndarray:
    """Give view ``target`` its observations of the live points seen in views ``refs`` (nearest
    first) but not yet in ``target``: project each point with the target's camera and align the
    patch of its observation in the nearest reference view there (COLMAP and ORB-SLAM search by
    projection; here sub-pixel by alignment). An observation is kept when the alignment
    converges within the resection threshold of the projection and does not land on another
    point's interest point. Returns the ids of the points whose track grew."""
    track = getattr(recon.source, "track", None)
    vt = recon.views[target]
    if track is None or vt.features is None:
        return np.zeros(0, np.int64)
    thr = cfg.resection.ransac_threshold_px
    h, w = vt.features.image_shape
    margin = vt.features.patch_size
    taken = set(recon.obs_point[recon.obs_view == target].tolist())
    grown = []
    for j in refs:
        sel = (recon.obs_view == j) & recon.alive[recon.obs_point]
        pids, feats = recon.obs_point[sel], recon.obs_feature[sel]
        fresh = ~np.isin(pids, list(taken))
        pids, feats = pids[fresh], feats[fresh]
        if len(pids) == 0:
            continue
        Xh = recon.points[pids] @ vt.P[:, :3].T + vt.P[:, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            xy = Xh[:, :2] / Xh[:, 2:3]
        inside = (Xh[:, 2] > 0) & (xy[:, 0] >= margin) & (xy[:, 0] <= w - 1 - margin) \
            & (xy[:, 1] >= margin) & (xy[:, 1] <= h - 1 - margin)
        pids, feats, xy = pids[inside], feats[inside], xy[inside]
        if len(pids) == 0:
            continue
        found, ok = track(j, target, recon.views[j].features, feats, vt.features, xy, thr)
        # an interest point of the target already standing for another point: not this one
        near = _nearest_linked(vt, found)
        ok &= near > 1.0
        if not ok.any():
            continue
        idx = _append_features(recon, target, found[ok])
        recon.add_observations(target, idx, pids[ok])
        grown.append(pids[ok])
        taken.update(pids[ok].tolist())
    return np.concatenate(grown) if grown else np.zeros(0, np.int64)


def _nearest_linked(view: View, xy: np.ndarray) -> np.ndarray:
    """Distance (K,) from pixels xy (K, 2) to the nearest interest point of view that stands for a 3D point."""
    linked = view.features.points[view.point_of_feature >= 0]
    if len(linked) == 0 or len(xy) == 0:
        return np.full(len(xy), np.inf)
    return cKDTree(linked).query(xy)[0]


def _last_registered(recon: Reconstruction, count: int) -> list[int]:
    return recon.registered_views[-count:]


def _retriangulate(recon: Reconstruction, point_ids: np.ndarray, cfg: Config) -> None:
    """Re-triangulate points from all their observations; keep the new position when it
    reprojects within the threshold everywhere."""
    sel = np.isin(recon.obs_point, point_ids)
    local = np.searchsorted(point_ids, recon.obs_point[sel])
    P_obs = np.stack([recon.views[v].P for v in recon.obs_view[sel]])
    xy = recon.observation_xy(sel)
    X = triangulate_tracks(P_obs, xy, local, len(point_ids), cfg.triangulation.lm_iterations)
    h = np.einsum("oij,oj->oi", P_obs[:, :, :3], X[local]) + P_obs[:, :, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.linalg.norm(h[:, :2] / h[:, 2:3] - xy, axis=1)
        worst = np.full(len(point_ids), np.inf)
        np.maximum.at(worst, local, np.where(h[:, 2] > 0, err, np.inf))
    ok = np.isfinite(worst) & (worst <= cfg.triangulation.max_reprojection_px)
    recon.points[point_ids[ok]] = X[ok]


def adjust(recon: Reconstruction, cfg: Config, free_views: list[int], free_points: np.ndarray | None = None,
           views_in_cost: list[int] | None = None) -> dict[str, Any]:
    """Bundle-adjust: ``free_views`` free; points free = ``free_points`` or, by default, every
    point those views observe; the cost holds every observation of the involved points (in
    ``views_in_cost`` only, if given). The calibrated pair (views 0, 1) never moves."""
    free_views = [v for v in free_views if v > 1]
    in_free_views = np.isin(recon.obs_view, free_views)
    if free_points is None:
        free_points = np.unique(recon.obs_point[in_free_views])
    involved = np.isin(recon.obs_point, free_points) | in_free_views
    if views_in_cost is not None:
        involved &= np.isin(recon.obs_view, views_in_cost)
    involved &= recon.alive[recon.obs_point]
    if not involved.any():
        return {"skipped": True}
    pc = cfg.pipeline
    # One model for every free camera of a BA: a view that needed a constrained model (its
    # 11-DOF camera was refused) is adjusted with it when it is free alone, and held fixed when
    # it is free together with cameras of the run's model.
    model_of = {v: recon.views[v].camera_model or pc.resolved_model() for v in free_views}
    models = set(model_of.values())
    model = models.pop() if len(models) == 1 else pc.resolved_model()
    free_views = [v for v in free_views if model_of[v] == model]
    cams = np.unique(recon.obs_view[involved])
    pts = np.unique(recon.obs_point[involved])
    problem = BundleProblem(
        Ps=np.stack([recon.views[v].P for v in cams]),
        free_cameras=np.isin(cams, free_views),
        points=recon.points[pts],
        free_points=np.isin(pts, free_points),
        obs_camera=np.searchsorted(cams, recon.obs_view[involved]),
        obs_point=np.searchsorted(pts, recon.obs_point[involved]),
        obs_xy=recon.observation_xy(involved),
        model=model,
        reference_K=np.stack([_reference_K(recon, v) for v in cams]),
    )
    result = bundle_adjust(problem, cfg.bundle)
    for i, v in enumerate(cams):
        if problem.free_cameras[i]:
            recon.views[v].P = result.Ps[i]
    recon.points[pts] = result.points
    m, n = len(cams), len(pts)
    rms_b, rms_a = result.rms_before, result.rms_after
    o = len(problem.obs_camera)
    return {"free_cameras": int(problem.free_cameras.sum()), "free_points": int(problem.free_points.sum()),
            "observations": o, "iterations": result.iterations, "seconds": result.seconds,
            "rms_before_px": rms_b, "rms_after_px": rms_a,
            "eq14_before": rms_b ** 2 * o / (m * n), "eq14_after": rms_a ** 2 * o / (m * n)}


def _drop_outliers(recon: Reconstruction, cfg: Config) -> int:
    """Remove observations reprojecting beyond the threshold (fixed, or relative to the median
    error: ``PipelineConfig.outlier_factor``), then points seen fewer than twice."""
    if len(recon.obs_view) == 0:
        return 0
    err = recon.observation_errors()
    threshold = 2.0 * cfg.triangulation.max_reprojection_px
    factor = cfg.pipeline.resolved_outlier_factor()
    counted = np.isfinite(err) & recon.alive[recon.obs_point]
    if factor is not None and counted.any():
        relative = max(cfg.pipeline.outlier_floor_px, factor * float(np.median(err[counted])))
        threshold = min(threshold, relative)
    bad = err > threshold
    recon.remove_observations(bad)
    lonely = np.flatnonzero(recon.alive & (recon.track_lengths() < 2))
    recon.remove_points(lonely)
    return int(bad.sum())


def _merge_points(recon: Reconstruction, keep: np.ndarray, drop: np.ndarray) -> int:
    """Merge point ``drop[i]`` into ``keep[i]``: its observations move over (unless the view
    already sees ``keep[i]``), it dies. Returns the number of merges done."""
    done = 0
    for p, q in zip(keep, drop):
        if p == q or not (recon.alive[p] and recon.alive[q]):
            continue
        views_p = set(recon.obs_view[recon.obs_point == p].tolist())
        obs_q = np.flatnonzero(recon.obs_point == q)
        clash = np.isin(recon.obs_view[obs_q], list(views_p))
        if clash.any():
            continue  # the same view would see both: not the same point
        recon.obs_point[obs_q] = p
        for o in obs_q:
            recon.views[recon.obs_view[o]].point_of_feature[recon.obs_feature[o]] = p
        recon.alive[q] = False
        done += 1
    return done


def close_loop(recon: Reconstruction, cfg: Config, span: int = 3, min_matches: int = 20) -> dict[str, Any]:
    """Loop closure for a sequence that comes back to its start: match each of the last ``span``
    registered views against the first ``span`` (cameras known, so under the epipolar
    constraint), link or merge the tracks they share, then one global BA (the pair fixed)."""
    reg = recon.registered_views
    if len(reg) < 2 * span + 1:
        return {"closed": False, "reason": "sequence too short"}
    firsts, lasts = reg[:span], reg[-span:]
    thr = cfg.resection.ransac_threshold_px
    links = merges = tried = 0
    for a in lasts:
        for b in firsts:
            va, vb = recon.views[a], recon.views[b]
            axis_a = decompose_projection(va.P)[1][2]
            axis_b = decompose_projection(vb.P)[1][2]
            if np.dot(axis_a, axis_b) < np.cos(np.radians(60.0)):
                continue  # looking too differently to share much
            m = _match(recon, b, a, F=fundamental_from_projections(vb.P, va.P))
            tried += len(m)
            if len(m) < min_matches:
                continue
            pb, pa = vb.point_of_feature[m.idx1], va.point_of_feature[m.idx2]
            both = (pa >= 0) & (pb >= 0) & (pa != pb)
            if both.any():
                # the same physical point reconstructed twice: close in space after drift
                d = np.linalg.norm(recon.points[pa[both]] - recon.points[pb[both]], axis=1)
                depth = np.linalg.norm(recon.points[pb[both]] - (-np.linalg.inv(vb.P[:, :3]) @ vb.P[:, 3]), axis=1)
                close = d < 0.02 * depth
                merges += _merge_points(recon, pb[both][close], pa[both][close])
            for pid, view, feats, other in ((pb, a, m.idx2, pa), (pa, b, m.idx1, pb)):
                cand = (pid >= 0) & (other < 0)
                if not cand.any():
                    continue
                err = np.linalg.norm(project(recon.views[view].P, recon.points[pid[cand]])
                                     - recon.views[view].features.points[feats[cand]], axis=1)
                ok = (err <= 4 * thr) & ~np.isin(pid[cand], recon.obs_point[recon.obs_view == view])
                pid_ok, f_ok = pid[cand][ok], feats[cand][ok]
                _, first = np.unique(pid_ok, return_index=True)
                recon.add_observations(view, f_ok[first], pid_ok[first])
                links += len(first)
    if links + merges == 0:
        return {"closed": False, "reason": "no shared points between the last and first views", "matches": tried}
    ba, removed = global_adjust(recon, cfg)
    return {"closed": True, "links": links, "merges": merges, "ba": ba, "removed_observations": removed}


# a global BA round that dropped at most this fraction of the observations is not repeated: it
# cannot move the solution measurably (box ring: 4 of 12,000 in three rounds, 0.13 s each;
# templeSparseRing drops 76, 14, 6 of 4,200)
_NEGLIGIBLE_DROP = 0.001


def global_adjust(recon: Reconstruction, cfg: Config, max_rounds: int = 4) -> tuple[dict[str, Any], int]:
    """Bundle-adjust every registered view (the pair fixed), drop the outliers, and again while
    the last round removed more than a negligible few (at most ``max_rounds``), as COLMAP's
    global BA does: the wrong observations left by drift hold the first solution away from the
    right one (measured on templeSparseRing: one image 22 mm off after one round, 12 mm after
    three; median 5.1 -> 3.9 mm). Returns (the last round's BA report with "rounds",
    "removed_per_round" and the first round's starting RMS added, observations removed)."""
    removed_per_round: list[int] = []
    rms_first = None
    while True:
        ba = adjust(recon, cfg, free_views=[i for i in recon.registered_views if i > 1])
        if ba.get("skipped"):  # nothing registered past the pair: no BA, so nothing to judge by
            return ba, 0
        removed = _drop_outliers(recon, cfg)
        removed_per_round.append(removed)
        rms_first = ba.get("rms_before_px") if rms_first is None else rms_first
        if removed <= _NEGLIGIBLE_DROP * ba.get("observations", 0) or len(removed_per_round) >= max_rounds:
            break
    ba.update(rounds=len(removed_per_round), removed_per_round=removed_per_round, rms_first_round_before_px=rms_first)
    return ba, sum(removed_per_round)


def finish(recon: Reconstruction, cfg: Config) -> dict[str, Any]:
    """After the last insertion: loop closure (accurate mode) and/or one global BA (``ba="final"``,
    unless closing the loop already ran it). In the accurate mode with the "focal" model, when no
    image's resection found a zoom (``PipelineConfig.hold_unzoomed``), the global BA at the end
    holds every image at the calibrated camera's intrinsics ("no_zoom" in the report)."""
    t = time.perf_counter()
    out: dict[str, Any] = {}
    pc = cfg.pipeline
    if pc.mode != "paper" and pc.loop_closure:
        out["loop_closure"] = close_loop(recon, cfg)
    closed = bool(out.get("loop_closure", {}).get("closed"))
    later = [v for v in recon.registered_views if v > 1]
    no_zoom = (pc.mode != "paper" and pc.hold_unzoomed and pc.resolved_model() == "focal" and bool(later)
               and not any(recon.views[v].zoomed for v in later) and (closed or pc.resolved_ba() == "final"))
    if no_zoom:
        # every image placed without a zoom: one lens setting for the whole sequence, the
        # calibrated one (a focal length per image only trades against the depth)
        out["no_zoom"] = True
        out["final_ba"] = global_adjust(recon, cfg.replace(pipeline={"camera_model": "fixed"}))[0]
    elif pc.resolved_ba() == "final" and not closed:  # closing ran one
        out["final_ba"] = global_adjust(recon, cfg)[0]
    out["seconds"] = time.perf_counter() - t
    return out


def reconstruct(images: list[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config = Config(),
                progress: Progress | None = None, source: Any = None) -> tuple[Reconstruction, dict[str, Any]]:
    """The whole incremental loop over an ordered sequence whose first two images are the
    calibrated pair (P_pair: their two (3, 4) cameras). Returns the reconstruction and a report."""
    t0 = time.perf_counter()
    n = len(images)
    if n < 2:
        raise StereoseedError("a sequence needs at least the two images of the calibrated pair")
    recon, init = initialise(images, names, P_pair, cfg, source)
    per_image: list[dict[str, Any]] = [{"image": names[0], "status": "calibrated"}, init]
    if progress:
        progress(2, n, f"pair: {init['new_points']} points")
    for k in range(2, n):
        try:
            rep = insert_view(recon, k, cfg)
            rep["status"] = "registered"
        except (StereoseedError, np.linalg.LinAlgError) as e:
            # a degenerate configuration the checks did not foresee is still one image's failure
            reason = str(e) if isinstance(e, StereoseedError) else f"{names[k]}: numerical failure ({e}); skipped"
            recon.views[k].P, recon.views[k].camera_model, recon.views[k].zoomed = None, None, False
            recon.views[k].status = f"failed: {reason}"
            _forget_view(recon, k)
            rep = {"image": names[k], "status": "failed", "reason": reason}
        per_image.append(rep)
        if progress:
            progress(k + 1, n, f"{names[k]}: {rep['status']}")
    final = finish(recon, cfg)
    summary = recon.reprojection_summary()
    pc = cfg.pipeline
    report = {
        "mode": pc.mode, "camera_model": pc.resolved_model(), "window": pc.resolved_window(), "ba": pc.resolved_ba(),
        "images": n, "registered": len(recon.registered_views),
        "points": int(len(recon.live_points()[0])), "reprojection": summary,
        "per_image": per_image, "final": final, "seconds": time.perf_counter() - t0,
        "config": cfg.to_dict(),
    }
    return recon, report


def _forget_view(recon: Reconstruction, k: int) -> None:
    """Undo a failed insertion: its observations, and points no longer seen twice."""
    recon.remove_observations(recon.obs_view == k)
    lonely = np.flatnonzero(recon.alive & (recon.track_lengths() < 2))
    recon.remove_points(lonely)
    if recon.views[k].features is not None:
        recon.views[k].point_of_feature[:] = -1


def load_sequence(images_source: str, calib_path: str) -> tuple[list[np.ndarray], list[str], list[np.ndarray]]:
    """Read an ordered image sequence (folder or list file) and the pair's calibration."""
    from .io import list_images, read_calibration, read_image

    paths = list_images(images_source)
    if len(paths) < 2:
        raise StereoseedError(f"{images_source}: {len(paths)} image(s); the calibrated pair needs two")
    P_pair = read_calibration(calib_path, [p.name for p in paths])
    images = [read_image(p) for p in paths]
    return images, [p.name for p in paths], P_pair


def save_outputs(recon: Reconstruction, report: dict[str, Any], out_dir: str) -> None:
    """cameras.json, sparse.ply and report.json in out_dir (atomic writes)."""
    from pathlib import Path

    from .io import write_json

    recon.save(out_dir)
    write_json(Path(out_dir) / "report.json", report)


def reconstruct_cli(args: Any) -> int:
    """`stereoseed reconstruct`: the CLI's thin layer over :func:`reconstruct`."""
    import dataclasses
    import sys

    from tqdm import tqdm

    images, names, P_pair = load_sequence(args.images, args.calib)
    pipeline_cfg = dataclasses.replace(Config().pipeline, mode=args.mode, camera_model=args.camera_model,
                                       window=args.window, ba=args.ba)
    cfg = dataclasses.replace(Config(), pipeline=pipeline_cfg)
    bar = None if args.quiet else tqdm(total=len(images), unit="image", file=sys.stderr)

    def progress(done: int, total: int, message: str) -> None:
        if bar is not None:
            bar.n = done
            bar.set_postfix_str(message[:40])
            bar.refresh()

    try:
        with warnings.catch_warnings():
            # Matching warns when a pair gives no robust F; the pipeline then tries the turned image
            # and the motion prior, and report.json says per image what held. Not for the terminal.
            warnings.simplefilter("ignore", RuntimeWarning)
            recon, report = reconstruct(images, names, P_pair, cfg, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    if getattr(args, "dense", False):
        from .dense import densify

        report["dense"] = densify(recon, cfg, args.out)
    save_outputs(recon, report, args.out)
    failed = [r for r in report["per_image"] if r.get("status") == "failed"]
    print(f"registered {report['registered']}/{report['images']} images, {report['points']} points, "
          f"reprojection RMS {report['reprojection']['rms_px']:.3f} px; wrote {args.out}")
    if report["final"].get("no_zoom"):
        print("  no image zoomed: every camera keeps the calibrated intrinsics (report.json: final.no_zoom)")
    for r in failed:
        print(f"  skipped: {r['reason']}")
    return 0
