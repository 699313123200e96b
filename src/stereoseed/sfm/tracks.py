"""Growing the reconstruction's tracks: new points triangulated from a pair, points followed
into more views by projection, points re-triangulated from their whole track, and new points
confirmed by a third view where repeated patterns defeat two-view matching.
"""
from __future__ import annotations

import numpy as np

from stereoseed.geometry.projection import fundamental_from_projections, project, project_homogeneous, project_per_observation
from stereoseed.estimators.config import TriangulationConfig
from stereoseed.matching.config import MatchingConfig
from stereoseed.sfm.config import TrackingConfig
from stereoseed.features.harris import Features, describe
from stereoseed.matching.containers import Matches
from stereoseed.matching.two_view import epipolar_band_mask
from stereoseed.geometry.neighbours import nearest_within
from stereoseed.scene.reconstruction import Reconstruction, View
from stereoseed.sfm.correspondence import CorrespondenceSource, optional
from stereoseed.estimators.triangulation import triangulate, triangulate_tracks

__all__ = ["colors_at", "triangulate_matches", "add_two_view_points", "new_points_three_view", "track_by_projection",
           "retriangulate"]


def colors_at(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """RGB colours (N, 3) uint8 at pixels xy (N, 2) of a BGR (or grey) image."""
    h, w = image.shape[:2]
    u = np.clip(np.rint(xy[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(xy[:, 1]).astype(int), 0, h - 1)
    return image[v, u][:, ::-1] if image.ndim == 3 else np.repeat(image[v, u][:, None], 3, axis=1)


def triangulate_matches(recon: Reconstruction, a: int, b: int, m: Matches,
                        triangulation: TriangulationConfig) -> tuple[np.ndarray, Matches]:
    """Triangulate matches between registered views a, b (linear + LM); keep those within the
    reprojection threshold, in front of both cameras and wide enough. -> (points (K, 3), matches)."""
    va, vb = recon.views[a], recon.views[b]
    x1, x2 = m.points(va.features, vb.features)
    tc = triangulation
    res = triangulate(np.stack([va.P, vb.P]), np.stack([x1, x2]), iterations=tc.lm_iterations)
    ok = res.valid(tc.max_reprojection_px, tc.min_angle_deg)
    return res.points[ok], m.subset(ok)


def add_two_view_points(recon: Reconstruction, a: int, b: int, m: Matches, triangulation: TriangulationConfig,
                        colour_view: int,
                        link_a: bool = True) -> np.ndarray:
    """New points from matches ``m`` between registered views a and b (:func:`triangulate_matches`),
    coloured from ``colour_view`` (a or b), observed in both; ``link_a`` False keeps a's interest
    points standing for what they stood for (the paper mode). Returns the new point ids."""
    X, kept = triangulate_matches(recon, a, b, m, triangulation)
    view = recon.views[colour_view]
    ids = recon.add_points(X, colors_at(view.image, view.features.points[kept.idx1 if colour_view == a
                                                                         else kept.idx2]))
    recon.add_observations(a, kept.idx1, ids, link=link_a)
    recon.add_observations(b, kept.idx2, ids)
    return ids


def new_points_three_view(recon: Reconstruction, a: int, b: int, c: int, tracking: TrackingConfig,
                          matching: MatchingConfig, triangulation: TriangulationConfig) -> np.ndarray:
    """New points from the interest points of views a, b that stand for none yet, when ZNCC
    cannot choose between repeated patterns: every pair within the epipolar band with ZNCC >=
    ``TrackingConfig.three_view_min_zncc`` is triangulated, and kept when a third registered
    view c has an interest point within ``three_view_max_px`` of its projection whose patch
    matches too; each interest point is used once (best score first). Returns the new point ids
    (observed in a, b and c)."""
    tc = tracking
    va, vb, vc = recon.views[a], recon.views[b], recon.views[c]
    fa = np.flatnonzero((va.point_of_feature < 0) & va.features.valid)
    fb = np.flatnonzero((vb.point_of_feature < 0) & vb.features.valid)
    fc = np.flatnonzero(vc.features.valid)
    none = np.zeros(0, np.int64)
    if min(len(fa), len(fb), len(fc)) == 0:
        return none
    band = epipolar_band_mask(fundamental_from_projections(va.P, vb.P), va.features.points[fa],
                              vb.features.points[fb], matching.epipolar_band_px)
    zab = va.features.desc[fa] @ vb.features.desc[fb].T
    ia, ib = np.nonzero(band & (zab >= tc.three_view_min_zncc))
    if len(ia) == 0:
        return none
    X, kept = triangulate_matches(recon, a, b, Matches(fa[ia], fb[ib], np.zeros(len(ia))), triangulation)
    ia, ib = kept.idx1, kept.idx2
    if len(ia) == 0:
        return none
    dist, nearest = nearest_within(vc.features.points[fc], project(vc.P, X), tc.three_view_max_px)
    ic = fc[np.minimum(nearest, len(fc) - 1)]
    score = np.minimum(np.einsum("ij,ij->i", va.features.desc[ia], vc.features.desc[ic]),
                       np.einsum("ij,ij->i", va.features.desc[ia], vb.features.desc[ib]))
    ok = (dist <= tc.three_view_max_px) & (score >= tc.three_view_min_zncc)
    keep = _one_to_one(ia, ib, ic, np.flatnonzero(ok)[np.argsort(-score[ok])])
    keep = keep[vc.point_of_feature[ic[keep]] < 0]
    if len(keep) == 0:
        return none
    ids = recon.add_points(X[keep], colors_at(vb.image, vb.features.points[ib[keep]]))
    recon.add_observations(a, ia[keep], ids)
    recon.add_observations(b, ib[keep], ids)
    recon.add_observations(c, ic[keep], ids)
    return ids


def _one_to_one(ia: np.ndarray, ib: np.ndarray, ic: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Greedy one-to-one selection of triplets in ``order`` (best first): an interest point is
    used once. A few hundred candidates at most. -> positions (K,) int64."""
    used_a, used_b, used_c, keep = set(), set(), set(), []
    for o in order:
        if ia[o] in used_a or ib[o] in used_b or ic[o] in used_c:
            continue
        used_a.add(ia[o])
        used_b.add(ib[o])
        used_c.add(ic[o])
        keep.append(o)
    return np.array(keep, np.int64)


def _tracked_features(view: View, xy: np.ndarray) -> Features:
    """Interest points at pixels xy (K, 2) of ``view`` found by tracking, with their patches."""
    f = view.features
    if f.gray is not None:
        desc, valid = describe(f.gray, xy, f.patch_size)
    else:
        desc, valid = np.zeros((len(xy), f.desc.shape[1]), np.float32), np.ones(len(xy), bool)
    return Features(xy, desc, valid, np.zeros(len(xy)), f.image_shape, f.gray)


def _clear_of_linked(view: View, xy: np.ndarray, radius: float) -> np.ndarray:
    """Whether no interest point of ``view`` that stands for a 3D point lies within ``radius``
    of each pixel of xy (K, 2): (K,) bool."""
    linked = view.features.points[view.point_of_feature >= 0]
    return np.isinf(nearest_within(linked, xy, radius)[0])


def track_by_projection(recon: Reconstruction, target: int, refs: list[int], tracking: TrackingConfig,
                        source: CorrespondenceSource | None = None) -> np.ndarray:
    """Give view ``target`` its observations of the live points seen in views ``refs`` (nearest
    first) but not yet in ``target``: project each point with the target's camera and align the
    patch of its observation in the reference view there (COLMAP and ORB-SLAM search by
    projection; here sub-pixel by alignment). An observation is kept when the alignment
    converges within ``TrackingConfig.max_shift_px`` of the projection and does not land on another
    point's interest point. Returns the ids of the points whose track grew."""
    track = optional(source, "track")
    vt = recon.views[target]
    if track is None or vt.features is None:
        return np.zeros(0, np.int64)
    thr = tracking.max_shift_px
    h, w = vt.features.image_shape
    margin = vt.features.patch_size
    taken = np.zeros(len(recon.points), bool)  # the points the target sees
    taken[recon.obs_point[recon.obs_view == target]] = True
    grown = []
    for j in refs:
        sel = (recon.obs_view == j) & recon.alive[recon.obs_point]
        pids, feats = recon.obs_point[sel], recon.obs_feature[sel]
        fresh = ~taken[pids]
        pids, feats = pids[fresh], feats[fresh]
        if len(pids) == 0:
            continue
        hom = project_homogeneous(vt.P, recon.points[pids])
        with np.errstate(invalid="ignore", divide="ignore"):
            xy = hom[:, :2] / hom[:, 2:3]
        inside = (hom[:, 2] > 0) & (xy[:, 0] >= margin) & (xy[:, 0] <= w - 1 - margin) \
            & (xy[:, 1] >= margin) & (xy[:, 1] <= h - 1 - margin)
        pids, feats, xy = pids[inside], feats[inside], xy[inside]
        if len(pids) == 0:
            continue
        found, ok = track(j, target, recon.views[j].features, feats, vt.features, xy, thr)
        ok &= _clear_of_linked(vt, found, tracking.min_distance_to_other_px)
        if not ok.any():
            continue
        idx = vt.append_features(_tracked_features(vt, found[ok]))
        recon.add_observations(target, idx, pids[ok])
        grown.append(pids[ok])
        taken[pids[ok]] = True
    return np.concatenate(grown) if grown else np.zeros(0, np.int64)


def retriangulate(recon: Reconstruction, point_ids: np.ndarray, triangulation: TriangulationConfig) -> None:
    """Re-triangulate points (K,) sorted ids from all their observations; a point takes the new
    position when it reprojects within the threshold, in front of every camera."""
    sel = np.isin(recon.obs_point, point_ids)
    local = np.searchsorted(point_ids, recon.obs_point[sel])
    views, of_view = np.unique(recon.obs_view[sel], return_inverse=True)
    P_obs = np.stack([recon.views[v].P for v in views])[of_view]  # composed once per view, not per observation
    xy = recon.observation_xy(sel)
    X = triangulate_tracks(P_obs, xy, local, len(point_ids), triangulation.lm_iterations)
    h, uv = project_per_observation(P_obs, X[local])
    err = np.linalg.norm(uv - xy, axis=1)
    worst = np.full(len(point_ids), -np.inf)  # a point without an observation stays -inf: not finite, not taken
    with np.errstate(invalid="ignore"):
        np.maximum.at(worst, local, np.where(h[:, 2] > 0, err, np.inf))
    ok = np.isfinite(worst) & (worst <= triangulation.max_reprojection_px)
    recon.points[point_ids[ok]] = X[ok]
