"""Registration of a weakly textured view by match propagation (Lhuillier & Quan, PAMI 2005).

Harris + ZNCC needs corners; an untextured object seen 20 degrees apart gives a handful of
sparse matches, too few (and too clustered) for a stable resection. When the sparse chain is
weak (fewer resection inliers than ``QuasiDenseConfig.weak_chain_inliers``), a second attempt:

1. seeds: the sparse robust-F matches I_{k-1} <-> I_k and SIFT matches (Lowe's ratio test);
2. quasi-dense propagation from the seeds *without* epipolar geometry (the disparity-gradient
   limit alone, :func:`stereoseed.matching.propagation.core.propagate` with ``F=None``);
3. the propagated matches resampled on a grid of I_{k-1}, one match (best ZNCC) per cell, and
   a robust F fitted on them (OpenCV USAC MAGSAC);
4. every live 3D point observed in I_{k-1} (interest point or an earlier insertion's grid
   point) chained to I_k through the propagated match of its pixel, kept when it lies on the
   robust F's epipolar lines; the camera resected from them (the sparse path's resector and
   its validation);
   The previous pair's quasi-dense points (I_{k-2} <-> I_{k-1} propagated under their known F,
   one per grid cell, triangulated: :func:`previous_pair_points`) are chained the same way, so
   the chain does not depend on the few Harris points of I_{k-1}. The camera is judged by the
   propagated matches' epipolar geometry (:func:`epipolar_agreement`): it zooms only when that
   says so, and it is refused (as is a weak sparse camera kept after the attempt) when it
   disagrees with them;
5. optionally (``QuasiDenseConfig.keep_tracks``, off: measured to cost accuracy, see
   docs/quasi_dense.md), after the commit (:func:`grow_quasi_dense`), the chained points'
   tracks extended into I_k and the grid matches triangulated as new points, observed at new
   (non-matching) interest points of both views.

Estimate, validate, commit: :func:`register_quasi_dense` (tried by
:func:`stereoseed.sfm.registration.reconsider.reconsider`) changes nothing; only :func:`grow_quasi_dense`
(called by the mapper after the commit, inside the insertion's checkpoint) changes the model.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import cv2
import numpy as np

from stereoseed.geometry.projection import epipolar_distances, fundamental_from_projections
from stereoseed.estimators.config import ResectionConfig, TriangulationConfig
from stereoseed.matching.config import MatchingConfig, PropagationConfig
from stereoseed.sfm.config import MotionPriorConfig, QuasiDenseConfig
from stereoseed.sfm.registration.settings import RegistrationSettings
from stereoseed.sfm.motion_prior import trusted_chain_inliers
from stereoseed.features.harris import Features, describe
from stereoseed.matching.alignment import PairCache, filter_localization
from stereoseed.matching.containers import Matches
from stereoseed.matching.pair import candidate_config
from stereoseed.matching.zncc import match_zncc
from stereoseed.matching.propagation.core import propagate
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.threads import in_background
from stereoseed.sfm.tracks import colors_at
from stereoseed.estimators.triangulation import triangulate
from stereoseed.sfm.correspondence import CorrespondenceSource, optional
from stereoseed.sfm.registration.base import (Candidate, FoundBy, Registration, Resector,
                                             consistent_chain)
from stereoseed.estimators.resection import ResectionResult
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.resampling import brought_down, frame_matrix, from_frame, to_frame

__all__ = ["QuasiDenseMatches", "weak_chain_limit", "sift_seeds", "grid_best", "propagate_pair", "register_quasi_dense",
           "dense_chain", "epipolar_agreement", "robust_f_agreement", "camera_epipolar_limit", "grow_quasi_dense"]

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class PairPoints:
    """Points of the previous pair's quasi-dense matches, not yet in the model: the registered
    view ``a`` propagated to the view ``other`` registered before it under their known F, one
    match per grid cell of a (cells without an observed point), triangulated. X (T, 3); xa
    (T, 2) pixels of a (whole pixels of the propagation's image of a, mapped back to the photo's
    when it was brought down); x_other (T, 2); scores (T,)."""

    other: int
    X: np.ndarray
    xa: np.ndarray
    x_other: np.ndarray
    scores: np.ndarray

    @classmethod
    def none(cls) -> "PairPoints":
        return cls(-1, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))


@dataclass(frozen=True)
class QuasiDenseMatches:
    """Propagated matches between a registered view a and a candidate b.

    matches: (M, 4) float64 rows (xa, ya, xb, yb) in the photos' pixels: xa, ya whole pixels of
    the propagation's image of a, xb, yb sub-pixel on the rows the registration reads (the
    grid's, the chained pixels'; every row with ``keep_tracks``: :func:`propagate_pair`), else
    whole (mapped back when the photos were brought down: ``ratio_a``, ``ratio_b``);
    scores: (M,) ZNCC; row_of_pixel: (H, W) int32, the row of ``matches`` of each pixel of the
    propagation's image of a (-1: unmatched; read it through :meth:`rows_at`); grid: (G,) int64 rows of ``matches``, the best one per grid cell of a;
    F: (3, 3) robust F of the grid matches (xb.T F xa = 0) or None; f_inlier: (G,) bool;
    report: counts and seconds (JSON-able)."""

    matches: np.ndarray
    scores: np.ndarray
    row_of_pixel: np.ndarray
    grid: np.ndarray
    F: np.ndarray | None
    f_inlier: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)
    pair: PairPoints | None = None  # the previous pair's points, chained through ``matches``
    # (2,) the ratios (new over old width, height) of a and b brought down for the propagation
    # (:func:`~stereoseed.geometry.resampling.brought_down`; row_of_pixel is indexed by the pixels of a's); None: the photos'
    ratio_a: np.ndarray | None = None
    ratio_b: np.ndarray | None = None

    def rows_at(self, xy: np.ndarray) -> np.ndarray:
        """:func:`_rows_at` of pixels xy (C, 2) of a (a's own pixels)."""
        return _rows_at(self.row_of_pixel, xy if self.ratio_a is None else to_frame(xy, self.ratio_a))

    def pair_chain(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The previous pair's points followed to b: (indices into ``pair`` (C,), xb (C, 2),
        scores (C,))."""
        if self.pair is None or len(self.pair.X) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
        row = self.rows_at(self.pair.xa)  # whole pixels of a, as the propagation's
        idx = np.flatnonzero(row >= 0)
        return idx, self.matches[row[idx], 2:], self.scores[row[idx]]


def weak_chain_limit(quasi_dense: QuasiDenseConfig, motion_prior: MotionPriorConfig, resection: ResectionConfig) -> int:
    """Resection inliers below which the sparse chain is weak and the quasi-dense attempt runs."""
    qc = quasi_dense
    if qc.weak_chain_inliers is not None:
        return qc.weak_chain_inliers
    return trusted_chain_inliers(motion_prior, resection)


def _grey_u8(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def sift_seeds(img_a: np.ndarray, img_b: np.ndarray, ratio: float) -> np.ndarray:
    """SIFT matches a -> b passing Lowe's ratio test: (S, 4) float64 rows (xa, ya, xb, yb).
    Images uint8 (grey or BGR). Some are wrong: propagation and the robust steps after it sort
    them out."""
    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(_grey_u8(img_a), None)
    kb, db = sift.detectAndCompute(_grey_u8(img_b), None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((0, 4))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if not good:
        return np.zeros((0, 4))
    return np.array([ka[g.queryIdx].pt + kb[g.trainIdx].pt for g in good], np.float64)


def grid_best(xy: np.ndarray, scores: np.ndarray, cell: int) -> np.ndarray:
    """Rows (G,) of the best-scoring point of each ``cell`` x ``cell`` pixel cell, for points xy
    (M, 2) with scores (M,); LQ05 resample a quasi-dense match set this way."""
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    cx = (xy[:, 0] // cell).astype(np.int64)
    cy = (xy[:, 1] // cell).astype(np.int64)
    key = cy * (int(cx.max()) + 1) + cx
    order = np.lexsort((-np.asarray(scores, np.float64), key))
    first = np.ones(len(order), bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return order[first]


def _foreground(image: np.ndarray, background_grey: int | None) -> np.ndarray:
    """The image with pixels darker than ``background_grey`` (8-bit grey) set to black, so that
    propagation (which needs texture) stays on the object; unchanged when None."""
    if background_grey is None:
        return image
    out = image.copy()
    out[_grey_u8(image) < background_grey] = 0
    return out


def _grid_and_f(res: Any, qc: Any, grid: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Matches (M, 4), scores (M,), grid rows (G,), robust F or None, F inliers (G,) of a
    :class:`~stereoseed.matching.propagation.core.PropagationResult` (grid: its grid rows when known)."""
    q, sc = res.matches, res.scores.astype(np.float64)
    if grid is None:
        grid = grid_best(q[:, :2], sc, qc.grid_cell_px)
    F, inlier = None, np.zeros(len(grid), bool)
    if len(grid) >= 8:  # the 8-point minimal set of OpenCV's USAC estimators
        F_est, mask = cv2.findFundamentalMat(q[grid, :2], q[grid, 2:], cv2.USAC_MAGSAC, qc.f_threshold_px,
                                             qc.f_confidence, qc.f_max_iters)
        if F_est is not None and F_est.shape == (3, 3) and mask is not None:
            F, inlier = F_est, mask.ravel().astype(bool)
    return q, sc, grid, F, inlier


def propagate_pair(img_a: np.ndarray, img_b: np.ndarray, seeds: np.ndarray, quasi_dense: QuasiDenseConfig,
                   propagation: PropagationConfig,
                   chained_pixels: Callable[[], np.ndarray] | None = None,
                   frame: tuple[np.ndarray, np.ndarray] | None = None) -> QuasiDenseMatches:
    """Steps 2-3: propagation from seeds (S, 4) without F, the grid resampling, a robust F.

    chained_pixels: the pixels (C, 2) of a whose matches are read besides the grid's, asked
    once the whole-pixel matches are known (it may wait for a result computed meanwhile): only
    those matches and the grid's get a sub-pixel position, the others keep whole pixels (a
    weak insertion reads a few thousand of 40-60 thousand). None: every match is refined.
    frame: the ratios (2,) of a and b when the images and seeds given are the photos brought
    down (:func:`~stereoseed.geometry.resampling.brought_down`); chained_pixels then gives the photo's pixels, and the matches
    and F come back in the photos' pixels."""
    qc = quasi_dense
    t = time.perf_counter()
    img_a, img_b = _foreground(img_a, qc.background_grey), _foreground(img_b, qc.background_grey)

    # the grid and the row map the refine_rows callbacks make (on the whole-pixel matches, whose
    # pixels of a and scores are the result's) serve the result too
    known: dict[str, np.ndarray] = {}

    def grid_rows(q: np.ndarray, sc: np.ndarray) -> np.ndarray:
        known["grid"] = grid_best(q[:, :2], sc.astype(np.float64), qc.grid_cell_px)
        return known["grid"]

    def read_rows(q: np.ndarray, sc: np.ndarray) -> np.ndarray:
        known["row_of_pixel"] = _row_of_pixel(q, img_a.shape[:2])
        pixels = chained_pixels()
        chained = _rows_at(known["row_of_pixel"], pixels if frame is None else to_frame(pixels, frame[0]))
        return np.union1d(grid_rows(q, sc), chained[chained >= 0])

    res = propagate(img_a, img_b, seeds, None, propagation,
                    refine_rows=None if chained_pixels is None else grid_rows if qc.second_pass else read_rows)
    q, sc, grid, F, inlier = _grid_and_f(res, qc, known.get("grid"))
    if qc.second_pass and F is not None:
        known.clear()
        res = propagate(img_a, img_b, q[grid[inlier]], F,
                        dataclasses.replace(propagation, epipolar_band_px=qc.chain_epipolar_px),
                        refine_rows=None if chained_pixels is None else read_rows)
        q, sc, grid, F2, inlier = _grid_and_f(res, qc, known.get("grid"))
        F = F2 if F2 is not None else F
    t_prop = time.perf_counter() - t
    row_of_pixel = known["row_of_pixel"] if "row_of_pixel" in known else _row_of_pixel(q, res.match_x.shape)
    report = {"seeds": int(len(seeds)), "seeds_used": res.n_seeds_used, "propagated": int(len(q)),
              "grid": int(len(grid)), "f_inliers": int(inlier.sum()),
              "seconds": {"propagation": t_prop}}
    if frame is None:
        return QuasiDenseMatches(q, sc, row_of_pixel, grid, F, inlier, report)
    ra, rb = frame  # back to the photos' pixels: x_small = S x, so F = S_b^T F_small S_a
    q = np.hstack([from_frame(q[:, :2], ra), from_frame(q[:, 2:], rb)])
    F = None if F is None else frame_matrix(rb).T @ F @ frame_matrix(ra)
    report["brought_down_to"] = [[int(img.shape[1]), int(img.shape[0])] for img in (img_a, img_b)]
    return QuasiDenseMatches(q, sc, row_of_pixel, grid, F, inlier, report, ratio_a=ra, ratio_b=rb)


def _row_of_pixel(q: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) int32: the row of the whole-pixel matches q (M, 4) at each pixel of a (-1: unmatched)."""
    row_of_pixel = np.full(shape, -1, np.int32)
    row_of_pixel[q[:, 1].astype(np.int64), q[:, 0].astype(np.int64)] = np.arange(len(q), dtype=np.int32)
    return row_of_pixel


def _rows_at(row_of_pixel: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(C,) int64: the match row at the pixel nearest to each point xy (C, 2) of a, -1 where
    that pixel is unmatched or outside the image."""
    h, w = row_of_pixel.shape
    r = np.rint(np.asarray(xy, np.float64).reshape(-1, 2)).astype(np.int64)
    inside = (r[:, 0] >= 0) & (r[:, 0] < w) & (r[:, 1] >= 0) & (r[:, 1] < h)
    row = np.full(len(r), -1, np.int64)
    row[inside] = row_of_pixel[r[inside, 1], r[inside, 0]]
    return row


def dense_chain(recon: Reconstruction, a: int, qd: QuasiDenseMatches) -> tuple[np.ndarray, ...]:
    """Step 4: the live points observed in view a, followed to b by the propagated match of
    their pixel (the sub-pixel offset from the pixel centre carried over).

    Returns features (C,) of a observing them, point ids (C,), xa (C, 2), xb (C, 2), scores
    (C,); each point once."""
    feats, pids, xa = _observed(recon, a)
    row = qd.rows_at(xa)
    ok = row >= 0
    # the offset from the match's pixel of a carried over to b: where the propagation ran on
    # the photos brought down, from its match's position mapped back, as in the small images
    if qd.ratio_a is None:
        xb = qd.matches[row[ok], 2:] + (xa[ok] - np.rint(xa[ok]))
    else:
        xb = qd.matches[row[ok], 2:] + (xa[ok] - qd.matches[row[ok], :2]) * qd.ratio_a / qd.ratio_b
    return feats[ok], pids[ok], xa[ok], xb, qd.scores[row[ok]]


def _observed(recon: Reconstruction, a: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The live points observed in view a, each once: features (C,) of a, point ids (C,), their
    pixels xa (C, 2)."""
    sel = (recon.obs_view == a) & recon.alive[recon.obs_point]
    feats, pids = recon.obs_feature[sel], recon.obs_point[sel]
    pids, first = np.unique(pids, return_index=True)  # paper mode: linked and unlinked at one pixel
    feats = feats[first]
    return feats, pids, recon.views[a].features.points[feats]


def _cell_keys(xy: np.ndarray, cell: int) -> np.ndarray:
    return (xy[:, 1] // cell).astype(np.int64) * 1_000_000 + (xy[:, 0] // cell).astype(np.int64)


def previous_pair_points(recon: Reconstruction, a: int, quasi_dense: QuasiDenseConfig, propagation: PropagationConfig,
                         triangulation: TriangulationConfig) -> PairPoints:
    """The previous pair's quasi-dense matches (view a and the registered view before it),
    propagated from the points both observe under their known F and triangulated; only grid
    cells of a where a observes no point yet (the sparse points chain on their own)."""
    before = recon.registered_before(a, 1)
    if not before:
        return PairPoints.none()
    b, cell = before[0], quasi_dense.grid_cell_px
    va, vb = recon.views[a], recon.views[b]
    bg = quasi_dense.background_grey
    observed = _cell_keys(recon.observation_xy(recon.obs_view == a), cell)  # an observation's point is alive

    (img_a, ra), (img_b, rb) = (brought_down(v.image, quasi_dense.max_side) for v in (va, vb))
    img_a, img_b = _foreground(img_a, bg), _foreground(img_b, bg)  # masked as propagate_pair masks
    seeds, F = recon.shared_pixels(a, b), fundamental_from_projections(va.P, vb.P)
    if ra is not None or rb is not None:  # propagated on the photos brought down, kept in their pixels
        ra, rb = (np.ones(2) if r is None else r for r in (ra, rb))
        seeds = np.hstack([to_frame(seeds[:, :2], ra), to_frame(seeds[:, 2:], rb)])
        F = np.linalg.inv(frame_matrix(rb)).T @ F @ np.linalg.inv(frame_matrix(ra))

    def photo(q: np.ndarray) -> np.ndarray:  # matches (M, 4) in the photos' pixels
        return q if ra is None else np.hstack([from_frame(q[:, :2], ra), from_frame(q[:, 2:], rb)])

    def free_grid(q: np.ndarray, scores: np.ndarray) -> np.ndarray:  # the rows kept (and refined)
        xy = photo(q)[:, :2]
        free = np.flatnonzero(~np.isin(_cell_keys(xy, cell), observed))
        return free[grid_best(xy[free], scores[free].astype(np.float64), cell)]

    res = propagate(img_a, img_b, seeds, F, propagation, refine_rows=free_grid)
    rows = free_grid(res.matches, res.scores)
    q, sc = photo(res.matches[rows]), res.scores[rows].astype(np.float64)
    tc = triangulation
    tri = triangulate(np.stack([va.P, vb.P]), np.stack([q[:, :2], q[:, 2:]]), iterations=tc.lm_iterations)
    ok = tri.valid(tc.max_reprojection_px, tc.min_angle_deg)
    return PairPoints(b, tri.points[ok], q[ok, :2], q[ok, 2:], sc[ok])


def localised_candidates(fa: Features, fb: Features, matching: MatchingConfig,
                         cache: PairCache | None = None) -> np.ndarray:
    """The sparse matcher's candidates without epipolar geometry that pass its relaxed
    localisation check, before any robust F: (S, 4) rows (xa, ya, xb, yb). A robust F needs
    many of them right; propagation only needs a few (a wrong seed grows a region no F
    explains). On the white dinosaur (dinoSparseRing 12 -> 13): 117 candidates, 22 localised,
    13 right; the robust F keeps none. ``cache``: the pair's, where the sparse matcher already
    scored and aligned these candidates (its first pass)."""
    mc = matching
    if fa.gray is None or fb.gray is None:
        return np.zeros((0, 4))
    m = match_zncc(fa, fb, candidate_config(mc, mc.first_pass_ratio), fb.image_shape[1], multiscale=True, cache=cache)
    m = filter_localization(m, fa, fb, mc.relaxed(), cache=cache)
    return np.hstack(m.points(fa, fb))


def epipolar_agreement(P_prev: np.ndarray, P: np.ndarray, qd: QuasiDenseMatches) -> float:
    """Median distance (px) of the robust F's grid inliers to the epipolar lines of the cameras
    P_prev (3, 4) of view a and P (3, 4) of view b: how well a camera for b agrees with the 2D
    propagated matches alone, whatever the 3D points it was resected from (inf: no inliers)."""
    g = qd.matches[qd.grid[qd.f_inlier]]
    if len(g) == 0:
        return float("inf")
    return float(np.median(epipolar_distances(fundamental_from_projections(P_prev, P), g[:, :2], g[:, 2:])))


def robust_f_agreement(qd: QuasiDenseMatches) -> float:
    """Median distance (px) of the robust F's grid inliers to its own lines: the floor a camera's
    :func:`epipolar_agreement` is compared with (inf: no F)."""
    g = qd.matches[qd.grid[qd.f_inlier]]
    if qd.F is None or len(g) == 0:
        return float("inf")
    return float(np.median(epipolar_distances(qd.F, g[:, :2], g[:, 2:])))


def camera_epipolar_limit(floor: float, quasi_dense: QuasiDenseConfig) -> float:
    """The largest :func:`epipolar_agreement` (px) a camera may have: ``camera_epipolar_factor``
    times the robust F's own median ``floor``, and never below the robust F's inlier threshold
    (``f_threshold_px``): on noise-free matches the floor is a tenth of a pixel and the chained
    points' own errors alone exceed twice that (a synthetic camera 5 mm off: 0.45 px, floor 0.12)."""
    qc = quasi_dense
    return max(qc.camera_epipolar_factor * floor, qc.f_threshold_px)


def _resect_validated(recon: Reconstruction, prev: int, cand: Candidate, qd: QuasiDenseMatches, X3: np.ndarray,
                      x: np.ndarray, scores: np.ndarray, settings: RegistrationSettings
                      ) -> tuple[ResectionResult, str | None] | str:
    """The camera of ``cand`` from the chained pairs X3 (N, 3) <-> x (N, 2), judged by the
    propagated matches' epipolar geometry, which does not depend on the chained points:

    * a zoom is not taken from the resection's BIC, whose errors are correlated here (a region
      grows from one seed; the chained points share the previous cameras' errors), so that
      hundreds of pairs make a small systematic gain look like evidence. The camera keeps the
      previous image's intrinsics unless the zoomed camera's :func:`epipolar_agreement` is at
      most ``QuasiDenseConfig.zoom_epipolar_ratio`` times the unzoomed one's;
    * the chosen camera's agreement must be within ``QuasiDenseConfig.camera_epipolar_factor``
      of the robust F's own (:func:`robust_f_agreement`; :func:`camera_epipolar_limit`).

    Returns (result, why an 11-DOF camera was refused or None), or the reason of the failure;
    the agreements go into ``qd.report``."""
    qc, vp = settings.quasi_dense, recon.views[prev]
    floor = robust_f_agreement(qd)
    qd.report["robust_f_median_px"] = floor
    found = Resector(recon, prev, cand, settings, may_zoom=False)(X3, x, scores)
    if settings.camera_model != CameraModel.FIXED:  # the run's model may find a zoom
        zoomed = Resector(recon, prev, cand, settings)(X3, x, scores)
        if not isinstance(zoomed, str) and zoomed[0].info.get("model") != CameraModel.FIXED:
            zoom_agrees = epipolar_agreement(vp.P, zoomed[0].P, qd)
            qd.report["zoomed_camera_median_px"] = zoom_agrees
            if isinstance(found, str) or zoom_agrees <= qc.zoom_epipolar_ratio * epipolar_agreement(vp.P, found[0].P, qd):
                found = zoomed
    if isinstance(found, str):
        return found
    agrees = epipolar_agreement(vp.P, found[0].P, qd)
    qd.report["camera_median_px"] = agrees
    if not agrees <= camera_epipolar_limit(floor, qc):
        return (f"{cand.name}: the quasi-dense camera disagrees with the propagated matches (their median distance "
                f"to its epipolar lines {agrees:.2f} px, to the robust F's {floor:.2f} px)")
    return found


def register_quasi_dense(recon: Reconstruction, prev: int, cand: Candidate, settings: RegistrationSettings,
                         source: CorrespondenceSource | None = None
                         ) -> tuple[Registration | str, QuasiDenseMatches | None]:
    """Steps 1-4 for candidate ``cand`` after the registered view ``prev``: (a
    :class:`Registration` (found_by "quasi-dense") or the reason, the propagated matches when
    they gave a robust F, else None). The previous pair's points do not depend on the
    candidate: they are propagated in a thread of their own while the candidate's seeds are
    found and propagated, until the propagation's sub-pixel step asks for the pixels they
    chain through (``seconds["previous_pair"]``: the time left to wait for them)."""
    waited = 0.0
    with in_background(previous_pair_points, recon, prev, settings.quasi_dense, settings.propagation,
                       settings.triangulation) as pair_points:

        def chained_pixels() -> np.ndarray:  # what the chain below reads of prev: its points, the pair's
            nonlocal waited
            t = time.perf_counter()
            pair = pair_points.result()
            waited += time.perf_counter() - t
            return np.vstack([_observed(recon, prev)[2], pair.xa])

        # grow_quasi_dense (keep_tracks) reads the pixels of points added after this: all refined
        qd = propagated_to_candidate(recon, source, prev, cand, settings.quasi_dense, settings.propagation,
                                     settings.matching, None if settings.quasi_dense.keep_tracks else chained_pixels)
        seconds = qd.report["seconds"]  # seeds, propagation; then previous_pair, resection
        seconds["propagation"] -= waited
        if qd.F is None:  # leaving the block still waits for the previous pair's points (they read recon)
            return f"{cand.name}: {len(qd.grid)} quasi-dense grid matches, no fundamental matrix fits them", None
        t = time.perf_counter()
        qd = dataclasses.replace(qd, pair=pair_points.result())
        seconds["previous_pair"] = waited + time.perf_counter() - t
    _, pids, x_prev, x_cand, scores = dense_chain(recon, prev, qd)
    pi, x_pair, s_pair = qd.pair_chain()
    X3 = np.vstack([recon.points[pids], qd.pair.X[pi]])
    x_prev, x_cand = np.vstack([x_prev, qd.pair.xa[pi]]), np.vstack([x_cand, x_pair])
    scores = np.concatenate([scores, s_pair])
    qc = settings.quasi_dense
    on_lines = epipolar_distances(qd.F, x_prev, x_cand) <= qc.chain_epipolar_px
    qd.report.update(chained=int(len(pids)), previous_pair_points=int(len(qd.pair.X)), chained_previous_pair=int(len(pi)),
                     chained_on_epipolar_lines=int(on_lines.sum()))
    if on_lines.sum() < settings.registration.min_chained_points:
        return (f"{cand.name}: only {int(on_lines.sum())} 3D points chained through {len(qd.matches)} propagated "
                f"matches (need {settings.registration.min_chained_points})"), qd
    t = time.perf_counter()
    found = _resect_validated(recon, prev, cand, qd, X3[on_lines], x_cand[on_lines], scores[on_lines], settings)
    seconds["resection"] = time.perf_counter() - t
    if isinstance(found, str):
        return found, qd
    res, refused = found
    qd.report["resection_inliers"] = int(res.inliers.sum())
    return Registration(cand, res, FoundBy.QUASI_DENSE, len(qd.grid), int(on_lines.sum()), None, refused, seconds,
                        quasi_dense=qd), qd


def propagated_to_candidate(recon: Reconstruction, source: CorrespondenceSource, prev: int, cand: Candidate,
                            quasi_dense: QuasiDenseConfig, propagation: PropagationConfig, matching: MatchingConfig,
                            chained_pixels: Callable[[], np.ndarray] | None) -> QuasiDenseMatches:
    """Steps 1-3: the seeds of (prev, cand) and their propagation (``chained_pixels``: as
    :func:`propagate_pair`'s)."""
    vp = recon.views[prev]
    t = time.perf_counter()
    pair_cache = optional(source, "pair_cache")  # a source without one computes afresh
    harris = localised_candidates(vp.features, cand.features, matching,
                                  pair_cache(vp.features, cand.features) if pair_cache else None)
    img_a, ra = brought_down(vp.image, quasi_dense.max_side)
    img_b, rb = brought_down(cand.image, quasi_dense.max_side)
    frame = None
    if ra is not None or rb is not None:  # seeds and propagation on the photos brought down
        frame = tuple(np.ones(2) if r is None else r for r in (ra, rb))
        harris = np.hstack([to_frame(harris[:, :2], frame[0]), to_frame(harris[:, 2:], frame[1])])
    sift = sift_seeds(img_a, img_b, quasi_dense.sift_ratio)
    seeds = np.vstack([harris, sift])
    t_seeds = time.perf_counter() - t
    qd = propagate_pair(img_a, img_b, seeds, quasi_dense, propagation, chained_pixels, frame)
    qd.report.update(harris_seeds=int(len(harris)), sift_seeds=int(len(sift)))
    qd.report["seconds"]["seeds"] = t_seeds
    return qd


def _grid_features(view_features: Features, xy: np.ndarray, patch_size: int) -> Features:
    """Interest points at grid matches xy (K, 2): tracked, not detected. Not ``valid``: the
    sparse matcher keeps to detected corners (a grid point on a smooth surface would only add
    candidates the localisation check refuses)."""
    desc, _ = describe(view_features.gray, xy, patch_size)
    return Features(xy, desc, np.zeros(len(xy), bool), np.zeros(len(xy)), view_features.image_shape,
                    view_features.gray)


def grow_quasi_dense(recon: Reconstruction, prev: int, k: int, reg: Registration, mode: Any,
                     quasi_dense: QuasiDenseConfig, resection: ResectionConfig,
                     triangulation: TriangulationConfig) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Step 5, after view k's camera was committed (and the mode added the sparse matches'
    points): the points of prev chained to k by the propagated matches gain an observation in
    k, and every grid match away from them becomes a new point (the mode's ``add_points``,
    which triangulates and filters as for sparse matches).

    Returns (new point ids, chained point ids now observed in k, report)."""
    qd: QuasiDenseMatches = reg.quasi_dense
    vp, vk = recon.views[prev], recon.views[k]
    pair_ids, pair_xa = _commit_pair_points(recon, prev, k, qd, resection, triangulation)
    feats, pids, x_prev, x_k, scores = dense_chain(recon, prev, qd)
    keep = ~np.isin(pids, pair_ids)  # just added, observed in k already
    feats, pids, x_prev, x_k, scores = feats[keep], pids[keep], x_prev[keep], x_k[keep], scores[keep]
    fresh = ~np.isin(pids, recon.points_seen_by(k))  # the sparse matches may have extended some already
    feats, x_prev, x_k, scores = feats[fresh], x_prev[fresh], x_k[fresh], scores[fresh]
    # grid cells already holding a chained point add no new point there
    cell = quasi_dense.grid_cell_px
    grid = qd.grid
    g = qd.matches[grid]
    g_keep = ~np.isin(_cell_keys(g[:, :2], cell), _cell_keys(np.vstack([x_prev, pair_xa]), cell))
    g, g_scores = g[g_keep], qd.scores[grid][g_keep]
    patch = vp.features.patch_size
    new_prev = vp.append_features(_grid_features(vp.features, g[:, :2], patch))
    new_k = vk.append_features(_grid_features(vk.features, np.vstack([x_k, g[:, 2:]]), patch))
    m = Matches(np.concatenate([feats, new_prev]), new_k, np.concatenate([scores, g_scores]))
    pid, chained, consistent = consistent_chain(recon, prev, k, m, resection.ransac_threshold_px)
    chain_points = pid[consistent]
    ids = mode.add_points(recon, prev, k, m, chained, consistent, chain_points, triangulation)
    report = {"previous_pair_points": int(len(pair_ids)), "chained_observations": int(len(chain_points)),
              "new_points": int(len(ids)), "grid_matches": int(len(g))}
    return np.concatenate([ids, pair_ids]), chain_points, report


def _commit_pair_points(recon: Reconstruction, prev: int, k: int, qd: QuasiDenseMatches,
                        resection: ResectionConfig, triangulation: TriangulationConfig
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The previous pair's points chained to k enter the model as three-view points (the
    other view, prev, k; triangulated again from the three) when they reproject in k within the
    resection threshold. Returns their ids (T,) and their pixels (T, 2) in prev."""
    pi, xk, _ = qd.pair_chain()
    if len(pi) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    pair, tc = qd.pair, triangulation
    views = [recon.views[v] for v in (pair.other, prev, k)]
    x = np.stack([pair.x_other[pi], pair.xa[pi], xk])
    tri = triangulate(np.stack([v.P for v in views]), x, iterations=tc.lm_iterations)
    ok = tri.valid(min(tc.max_reprojection_px, resection.ransac_threshold_px), tc.min_angle_deg)
    x = x[:, ok]
    ids = recon.add_points(tri.points[ok], colors_at(views[2].image, x[2]))
    patch = views[0].features.patch_size
    for v, xy in zip((pair.other, prev, k), x):
        recon.add_observations(v, recon.views[v].append_features(_grid_features(recon.views[v].features, xy, patch)),
                               ids)
    return ids, x[1]
