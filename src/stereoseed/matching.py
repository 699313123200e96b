"""ZNCC matching of interest points, epipolar filtering, robust F, and match chaining.

Paper §4.1 steps 3-4 and §4.2: each point of I_1 is matched to the point of I_2 with the best
normalised cross-correlation above a threshold; false matches are removed by the epipolar
constraint (F from the two calibrated cameras) or, when only the images are known, by a robust
estimate of F. The matches of consecutive pairs are chained to find the points of I_{k-1} seen in
both I_{k-2} and I_k (the paper's B_{k-1}).

Descriptors are zero-mean unit-norm patches (:mod:`stereoseed.features`), so the ZNCC of every
pair of points is a float32 matrix product; every test of :func:`match_zncc` is a mask on that
matrix. :func:`match_pair` is the matcher the pipeline calls. What it adds to the paper's recipe
(11x11 ZNCC > 0.8, mutual best, epipolar band), each measured on the synthetic box (20 degrees
between views; tests/test_matching.py, benchmarks/bench_matching.py):

* guided matching (Hartley & Zisserman §11.6): with a known or estimated F the epipolar band
  restricts the candidates *before* the best one is chosen, so a point whose true partner is not
  the best score in a 2-D window can still be matched along its band;
* a uniqueness test in both directions for guided candidates (Lowe's ratio on the descriptor
  distance sqrt(2 - 2 ZNCC)), blind to competitors within half a patch of the winner (they
  sample the same structure): this is what rejects the box's identical dark squares;
* patches of image 2 also sampled at 1/1.2 and 1.2 times the scale, for zooming cameras;
* a localisation check (:func:`align_matches`): affine Lucas-Kanade on the two patches gives
  the position of x1 in image 2 to a few hundredths of a pixel; a match is kept only if the
  detected point lies within 0.75 px of it and the aligned ZNCC exceeds 0.9. Independent Harris
  detections of one point drift apart under foreshortening (10-20 % by more than 1 px at 20
  degrees) and the unaligned ZNCC cannot tell; this check can, so the candidate thresholds can
  be looser (ZNCC > 0.6, ratio 0.9) and keep many more true matches.

The same alignment gives sub-pixel correspondences: :func:`refine_features` moves the matched
points of image 2 onto their partners (median error ~0.03 px instead of ~0.3 px).
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
from numba import njit
import numpy as np
from scipy.spatial import cKDTree

from .camera import epipolar_distances
from .config import FeatureConfig, MatchingConfig
from .errors import StereoseedError
from .features import DEFAULT_MIN_PATCH_STD, Features, describe, describe_scaled, extract_features, sample_bilinear

__all__ = [
    "Matches",
    "zncc_matrix",
    "match_zncc",
    "Alignment",
    "align_matches",
    "PairCache",
    "filter_localization",
    "refine_features",
    "filter_epipolar",
    "filter_fundamental_ransac",
    "match_pair",
    "chain",
    "draw_matches",
]

# Lowe's ratio on descriptor distances d = sqrt(2 - 2 ZNCC): the best candidate must be at most
# this fraction of the distance of the best competitor. 0.8 is Lowe's (IJCV 2004) choice.
DEFAULT_MAX_RATIO = 0.8
_ZNCC_EPS = 1e-5  # float32 resolution of a ZNCC near 1 (dot product of 121 float32 terms)
# Guided matching (candidates already restricted to an epipolar band, then checked by the
# localisation test) can afford looser candidate thresholds; see match_pair.
DEFAULT_GUIDED_MAX_RATIO = 0.9
# Scales at which image-2 patches are also sampled (zoom between views): with 1/1.2, 1 and 1.2
# any scale ratio in [0.76, 1.31] is within 9.5 % of a sampled one, which 11x11 ZNCC tolerates
# (the synthetic ring's focal jitter makes ratios up to ~1.2; without them one pair in six
# found no F).
DEFAULT_SCALES = (1 / 1.2, 1.2)
# Candidate threshold of match_pair: below the paper's 0.8 on purpose, the localisation check
# being the acceptance test (true matches under foreshortening score 0.6-0.8 unaligned).
DEFAULT_CANDIDATE_MIN_ZNCC = 0.6
# Minimum number of inliers for a robust F to be trusted: F has 7 degrees of freedom and the
# minimal sample is 7-8 points, so a consensus barely above the minimal sample is not evidence.
DEFAULT_MIN_F_INLIERS = 15
# Localisation check (align_matches): patch side of the affine alignment (a little larger than
# the descriptor patch: six parameters need more pixels than a score), largest accepted distance
# between the aligned and the detected position, and the aligned-ZNCC acceptance threshold.
DEFAULT_ALIGN_PATCH = 15
DEFAULT_MAX_SHIFT_PX = 0.75
DEFAULT_ALIGNED_MIN_ZNCC = 0.9


@dataclass(frozen=True)
class Matches:
    """Correspondences between two feature arrays.

    idx1: (M,) int64 indices into the points of image 1; idx2: (M,) int64 into image 2;
    score: (M,) float64 ZNCC of each match, higher is better (the resection chooses points by
    it): of the descriptor patches after :func:`match_zncc`, of the affinely aligned patches after
    :func:`filter_localization` / :func:`match_pair`.
    """

    idx1: np.ndarray
    idx2: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        idx1 = np.asarray(self.idx1, dtype=np.int64).reshape(-1)
        idx2 = np.asarray(self.idx2, dtype=np.int64).reshape(-1)
        score = np.asarray(self.score, dtype=np.float64).reshape(-1)
        if not (idx1.shape == idx2.shape == score.shape):
            raise StereoseedError(
                f"Matches arrays differ in length: {idx1.shape}, {idx2.shape}, {score.shape}"
            )
        object.__setattr__(self, "idx1", idx1)
        object.__setattr__(self, "idx2", idx2)
        object.__setattr__(self, "score", score)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64))

    def __len__(self) -> int:
        return int(self.idx1.shape[0])

    def subset(self, mask: np.ndarray) -> Matches:
        """The matches selected by a (M,) bool mask, an array of positions or a slice."""
        if not isinstance(mask, slice):
            mask = np.asarray(mask)
        return Matches(self.idx1[mask], self.idx2[mask], self.score[mask])

    def sorted_by_score(self) -> Matches:
        """The same matches, best ZNCC first."""
        return self.subset(np.argsort(-self.score, kind="stable"))

    def points(
        self, kp1: Features | np.ndarray, kp2: Features | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Matched positions: x1 (M, 2) float64 in image 1, x2 (M, 2) float64 in image 2."""
        return _as_points(kp1)[self.idx1], _as_points(kp2)[self.idx2]


def _as_points(kp: Features | np.ndarray) -> np.ndarray:
    pts = kp.points if isinstance(kp, Features) else kp
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


def _warn(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def zncc_matrix(desc1: np.ndarray, desc2: np.ndarray) -> np.ndarray:
    """All ZNCC scores: (N1, D) x (N2, D) zero-mean unit-norm descriptors -> (N1, N2) float32."""
    return np.asarray(desc1, np.float32) @ np.asarray(desc2, np.float32).T


def _masked_scores(desc1: np.ndarray, desc2: list[np.ndarray], cand: np.ndarray) -> np.ndarray:
    """ZNCC of the candidate pairs, best over several descriptor sets of image 2.

    desc1: (N1, D); desc2: list of (N2, D) (NaN rows: not available at that scale); cand: (N1, N2)
    bool. Returns (N1, N2) float32 with -inf outside ``cand``. A sparse mask (e.g. an epipolar
    band) is scored pair by pair, a dense one by matrix products.
    """
    n1, n2 = cand.shape
    if np.count_nonzero(cand) * 8 < n1 * n2:
        ii, jj = np.nonzero(cand)
        s = np.full((n1, n2), -np.inf, np.float32)
        best = np.full(len(ii), -np.inf, np.float32)
        for d2 in desc2:
            z = np.einsum("ij,ij->i", desc1[ii], d2[jj])
            np.fmax(best, z, out=best)  # fmax: NaN (unavailable) loses
        s[ii, jj] = best
        return s
    dense = zncc_matrix(desc1, desc2[0])
    for d2 in desc2[1:]:
        np.fmax(dense, zncc_matrix(desc1, d2), out=dense)
    np.copyto(dense, np.float32(-np.inf), where=~cand | np.isnan(dense))
    return dense


def epipolar_band_mask(
    F: np.ndarray, x1: np.ndarray, x2: np.ndarray, band_px: float
) -> np.ndarray:
    """(N1, N2) bool: pairs within ``band_px`` of each other's epipolar line in both images.

    Same distance as :func:`stereoseed.camera.epipolar_distances` (max of both one-sided
    distances), for all pairs at once: the numerator |x2^T F x1| is shared, so the max distance
    is that numerator over the smaller of the two line normals.
    """
    return _candidate_mask(x1, x2, np.inf, F, band_px)


def _candidate_mask(centre: np.ndarray, x2: np.ndarray, radius_px: float, F: np.ndarray | None = None,
                   band_px: float = np.inf, x1: np.ndarray | None = None) -> np.ndarray:
    """(N1, N2) bool: pairs with x2[j] (N2, 2) within ``radius_px`` of centre[i] (N1, 2) and,
    with F (3, 3), within ``band_px`` of the epipolar lines of x1[i] (N1, 2; default centre) in
    both images (:func:`epipolar_band_mask`). One pass over the pairs, no (N1, N2) temporaries."""
    centre = np.ascontiguousarray(centre, np.float64).reshape(-1, 2)
    x2 = np.ascontiguousarray(x2, np.float64).reshape(-1, 2)
    x1 = centre if x1 is None else np.ascontiguousarray(x1, np.float64).reshape(-1, 2)
    if len(x1) != len(centre):
        raise StereoseedError(f"x1 has {len(x1)} points, centre {len(centre)}: one centre per point")
    if F is None:  # every pair inside the band: 0 <= inf
        lines2, norm2, norm1 = np.zeros((len(x1), 3)), np.ones(len(x1)), np.ones(len(x2))
        band_px = np.inf
    else:
        F = np.asarray(F, np.float64)
        lines2 = np.hstack([x1, np.ones((len(x1), 1))]) @ F.T  # (N1, 3) epipolar lines in image 2
        lines1 = np.hstack([x2, np.ones((len(x2), 1))]) @ F  # (N2, 3) epipolar lines in image 1
        norm2 = np.hypot(lines2[:, 0], lines2[:, 1])
        norm1 = np.hypot(lines1[:, 0], lines1[:, 1])
    return _candidate_kernel(centre, x2, float(radius_px) ** 2, np.ascontiguousarray(lines2), norm2, norm1,
                             float(band_px))


@njit(cache=True)
def _candidate_kernel(centre, x2, radius2, lines2, norm2, norm1, band):
    """The mask of :func:`_candidate_mask` from the epipolar lines in image 2 (N1, 3) and the
    normals' lengths of the lines in image 2 (N1,) and image 1 (N2,)."""
    n1, n2 = centre.shape[0], x2.shape[0]
    mask = np.empty((n1, n2), np.bool_)
    xs, ys = x2[:, 0].copy(), x2[:, 1].copy()
    limit1 = band * norm1
    for i in range(n1):
        cx, cy = centre[i, 0], centre[i, 1]
        a, b, c = lines2[i, 0], lines2[i, 1], lines2[i, 2]
        limit2 = band * norm2[i]
        # |x2^T F x1| / norm is the distance in the image of that norm's line: the pair passes
        # when the numerator is within band times the smaller norm (no division by a zero
        # norm); without branches, so the loop vectorises
        for j in range(n2):
            dx, dy = xs[j] - cx, ys[j] - cy
            num = abs(a * xs[j] + b * ys[j] + c)
            mask[i, j] = (dx * dx + dy * dy <= radius2) & (num <= limit2) & (num <= limit1[j])
    return mask


@njit(cache=True)
def _best_per_row_and_column(s):
    """(N1, N2) scores -> best column of each row (N1,), its score (N1,), best row of each
    column (N2,); the first of equal maxima, as np.argmax. One pass."""
    n1, n2 = s.shape
    best_col = np.zeros(n1, np.int64)
    best_score = np.full(n1, -np.inf, np.float32)
    best_row = np.zeros(n2, np.int64)
    col_score = np.full(n2, -np.inf, np.float32)
    for i in range(n1):
        for j in range(n2):
            v = s[i, j]
            if v > best_score[i]:
                best_score[i] = v
                best_col[i] = j
            if v > col_score[j]:
                col_score[j] = v
                best_row[j] = i
    return best_col, best_score, best_row


def _neighbours(pts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Points within ``radius`` of each point (itself included), as CSR arrays.

    pts: (N, 2). Returns indptr (N + 1,) and indices: the neighbours of point k are
    ``indices[indptr[k]:indptr[k + 1]]``.
    """
    n = len(pts)
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray") if n else np.zeros((0, 2), int)
    own = np.arange(n)
    a = np.concatenate([pairs[:, 0], pairs[:, 1], own])
    b = np.concatenate([pairs[:, 1], pairs[:, 0], own])
    order = np.argsort(a, kind="stable")
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(a, minlength=n), out=indptr[1:])
    return indptr, b[order].astype(np.int64)


def _competitor(
    s: np.ndarray, rows: np.ndarray, winners: np.ndarray, indptr: np.ndarray, indices: np.ndarray
) -> np.ndarray:
    """Best score of each row ``rows[k]`` of ``s`` outside the neighbourhood of its winning
    column ``winners[k]`` (neighbourhoods from :func:`_neighbours`, winner included).

    s: (R, C) float32 with -inf for non-candidates; it is modified and restored. -> (K,) float32,
    -inf when there is no competitor.
    """
    if s.shape[1] == 0 or len(rows) == 0:
        return np.full(len(rows), -np.inf, np.float32)
    counts = indptr[winners + 1] - indptr[winners]
    rr = np.repeat(rows, counts)
    first = np.repeat(indptr[winners], counts)
    offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cc = indices[first + offset]
    saved = s[rr, cc]
    s[rr, cc] = -np.inf
    comp = s[rows].max(axis=1)
    s[rr, cc] = saved
    return comp


def _scaled_descriptors(f2: Features, v2: np.ndarray, scales: tuple[float, ...]) -> list[np.ndarray]:
    """Descriptors of the points ``v2`` of image 2 at scale 1 and at ``scales``: zoom changes
    between the views (the moving camera's focal length varies), so the patches of image 1 are
    also compared with patches of image 2 resampled at other scales, and each pair keeps its
    best score. NaN rows: not available at that scale."""
    desc2 = [f2.desc[v2]]
    if f2.gray is not None:
        for sc in scales:
            if sc != 1.0:
                d2s, ok2 = describe_scaled(f2.gray, f2.points[v2], f2.patch_size, sc)
                d2s[~ok2] = np.nan  # never a candidate at that scale
                desc2.append(d2s)
    return desc2


def match_zncc(
    f1: Features,
    f2: Features,
    config: MatchingConfig = MatchingConfig(),
    image_width: float | None = None,
    *,
    F: np.ndarray | None = None,
    band_px: float | None = None,
    predicted: np.ndarray | None = None,
    prior_radius_px: float | None = None,
    max_ratio: float | None = DEFAULT_MAX_RATIO,
    unique_exclusion_px: float | None = None,
    scales: tuple[float, ...] = (),
    cache: PairCache | None = None,
) -> Matches:
    """Match two feature sets by ZNCC.

    f1, f2: features of images 1 and 2 (descriptors of the same patch size).
    image_width: width (px) that scales ``config.search_radius``; default f2's image width.
    A pair (i, j) is a candidate when both descriptors are valid and x2_j lies within
    ``config.search_radius * image_width`` px of x1_i (of ``predicted[i]`` instead, (N1, 2), if
    given, within ``prior_radius_px``, default the same radius), and, if F (3, 3) is given,
    within ``band_px`` (default ``config.epipolar_band_px``) of the epipolar lines in both images.
    Each point of image 1 keeps its best candidate if its ZNCC exceeds ``config.min_zncc``, if it
    is also the best of the point of image 2 among its candidates (``config.mutual``), and if it
    passes the uniqueness test in both directions: ``sqrt(1 - best) < max_ratio *
    sqrt(1 - competitor)``, where the competitor is the best other candidate farther than
    ``unique_exclusion_px`` (default ``config.patch_size / 2``) from the winner. ``max_ratio``
    None (or >= 1) disables it. A ``cache`` (:class:`PairCache` for (f1, f2)) keeps the scores
    of all pairs for the next call on the same features.
    Returns Matches sorted by decreasing score; empty (with a warning) if either set is empty.
    """
    x1 = _as_points(f1)
    x2 = _as_points(f2)
    n1, n2 = len(x1), len(x2)
    if n1 == 0 or n2 == 0:
        _warn(f"no matches: {n1} and {n2} features")
        return Matches.empty()
    if f1.desc.shape[1] != f2.desc.shape[1]:
        raise StereoseedError(
            f"descriptor lengths differ ({f1.desc.shape[1]} vs {f2.desc.shape[1]}): "
            "extract both feature sets with the same patch_size"
        )
    v1 = np.flatnonzero(f1.valid)
    v2 = np.flatnonzero(f2.valid)
    if len(v1) == 0 or len(v2) == 0:
        _warn("no matches: no valid descriptor in one of the images")
        return Matches.empty()
    x1v, x2v = x1[v1], x2[v2]

    width = float(image_width if image_width is not None else f2.image_shape[1])
    radius = float(config.search_radius) * width
    centre = x1v
    if predicted is not None:
        predicted = np.asarray(predicted, np.float64).reshape(-1, 2)
        if len(predicted) != n1:
            raise StereoseedError(f"predicted has {len(predicted)} rows, f1 has {n1} points")
        centre = predicted[v1]
        radius = float(prior_radius_px) if prior_radius_px is not None else radius
    band = float(config.epipolar_band_px if band_px is None else band_px)
    cand = _candidate_mask(centre, x2v, radius, F, band, x1=x1v)

    if cache is not None and cache.covers(f1, f2):
        full = cache.scores.get(tuple(scales))
        if full is None:
            full = _masked_scores(f1.desc[v1], _scaled_descriptors(f2, v2, scales), np.ones(cand.shape, bool))
            cache.scores[tuple(scales)] = full
        s = np.where(cand, full, np.float32(-np.inf))
    else:
        s = _masked_scores(f1.desc[v1], _scaled_descriptors(f2, v2, scales), cand)
    best2, score, best1 = _best_per_row_and_column(s)
    keep = score > config.min_zncc
    if config.mutual:
        keep &= best1[best2] == np.arange(len(v1))

    if max_ratio is not None and max_ratio < 1.0:
        excl = float(config.patch_size) / 2.0
        if unique_exclusion_px is not None:
            excl = float(unique_exclusion_px)
        rows = np.flatnonzero(keep)
        if len(rows):
            cols = best2[rows]
            # Competitors in image 2 (other columns of the row) and in image 1 (other rows of
            # the column), ignoring those within excl px of the winner.
            comp2 = _competitor(s, rows, cols, *_neighbours(x2v, excl))
            comp1 = _competitor(s.T, cols, rows, *_neighbours(x1v, excl))
            comp = np.maximum(comp1, comp2).astype(np.float64)
            best = score[rows].astype(np.float64)
            # sqrt(1 - best) < r sqrt(1 - comp)  <=>  1 - best < r^2 (1 - comp); -inf passes.
            # Float32 scores of identical patches differ by ~1e-7 around 1: distances below
            # _ZNCC_EPS are ties, which must fail.
            d_best = np.maximum(1.0 - best, 0.0) + _ZNCC_EPS
            d_comp = np.maximum(1.0 - comp, 0.0) + _ZNCC_EPS
            unique = d_best < max_ratio**2 * d_comp
            keep[rows[~unique]] = False

    rows = np.flatnonzero(keep)
    m = Matches(v1[rows], v2[best2[rows]], score[rows])
    return m.sorted_by_score()


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`align_matches`, one row per match.

    x2: (M, 2) float64 position in image 2 of the point ``x1`` of image 1 (sub-pixel, from the
    affine alignment of the two patches); affine: (M, 2, 2) float64 local linear map from image 1
    to image 2 around the match; zncc: (M,) float64 ZNCC of the aligned patches (-1 where not
    converged); converged: (M,) bool.
    """

    x2: np.ndarray
    affine: np.ndarray
    zncc: np.ndarray
    converged: np.ndarray

    def shift(self, kp2: Features | np.ndarray, matches: Matches) -> np.ndarray:
        """(M,) distance between the aligned position and the detected point of image 2."""
        return np.linalg.norm(self.x2 - _as_points(kp2)[matches.idx2], axis=1)


class PairCache:
    """What matching one pair several times (robust F, guided, relaxed, known F, then the
    sub-pixel refinement) would otherwise compute again: the ZNCC scores of all valid pairs
    (per set of scales) and the alignment of each (idx1, idx2) pair. Valid for the two Features
    objects it was made for (identity).
    """

    def __init__(self, f1: Features, f2: Features):
        self.f1, self.f2 = f1, f2
        self.scores: dict[tuple, np.ndarray] = {}
        self.params: tuple | None = None
        self.codes = np.zeros(0, np.int64)
        self.rows = Alignment(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0, bool))

    def covers(self, f1: Features, f2: Features) -> bool:
        return f1 is self.f1 and f2 is self.f2

    def lookup(self, codes: np.ndarray) -> np.ndarray:
        """(M,) row of each code in the cache, -1 where absent."""
        pos = np.minimum(np.searchsorted(self.codes, codes), max(len(self.codes) - 1, 0))
        hit = (self.codes[pos] == codes) if len(self.codes) else np.zeros(len(codes), bool)
        return np.where(hit, pos, -1)

    def add(self, codes: np.ndarray, al: Alignment) -> None:
        codes = np.concatenate([self.codes, codes])
        order = np.argsort(codes, kind="stable")
        r = self.rows
        self.codes = codes[order]
        self.rows = Alignment(np.concatenate([r.x2, al.x2])[order], np.concatenate([r.affine, al.affine])[order],
                              np.concatenate([r.zncc, al.zncc])[order], np.concatenate([r.converged, al.converged])[order])


@njit(cache=True, fastmath=True)
def _sample_normalised(img, A, t, r, out):
    """Patch of img at u -> A u + t (u in [-r, r]^2), zero-mean; returns its norm and whether
    every sample lies inside the image."""
    h, w = img.shape
    # the warped square is inside iff its four corners are (the warp is affine)
    inside = True
    for cy in (-r, r):
        for cx in (-r, r):
            x = t[0] + A[0, 0] * cx + A[0, 1] * cy
            y = t[1] + A[1, 0] * cx + A[1, 1] * cy
            if not (0.0 <= x <= w - 2.0 and 0.0 <= y <= h - 2.0):
                inside = False
    n = 0
    total = 0.0
    for iy in range(-r, r + 1):
        x = t[0] + A[0, 1] * iy - A[0, 0] * r
        y = t[1] + A[1, 1] * iy - A[1, 0] * r
        for ix in range(2 * r + 1):
            if inside:  # fast path: no clamping
                x0 = int(x)
                y0 = int(y)
                fx = x - x0
                fy = y - y0
                v = ((img[y0, x0] * (1.0 - fx) + img[y0, x0 + 1] * fx) * (1.0 - fy)
                     + (img[y0 + 1, x0] * (1.0 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)
            else:
                v = sample_bilinear(img, x, y)
            out[n] = v
            total += v
            n += 1
            x += A[0, 0]
            y += A[1, 0]
    mean = total / n
    norm = 0.0
    for i in range(n):
        out[i] -= mean
        norm += out[i] * out[i]
    return np.sqrt(norm), inside


@njit(cache=True, fastmath=True)
def _invert(a, out, work):
    """Inverse of the small (n, n) matrix a into out (Gauss-Jordan, partial pivoting); work is
    (n, 2n) scratch. Allocation-free, like the rest of the per-match alignment work."""
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            work[i, j] = a[i, j]
            work[i, n + j] = 1.0 if i == j else 0.0
    for col in range(n):
        piv = col
        for i in range(col + 1, n):
            if abs(work[i, col]) > abs(work[piv, col]):
                piv = i
        if piv != col:
            for j in range(2 * n):
                tmp = work[col, j]
                work[col, j] = work[piv, j]
                work[piv, j] = tmp
        d = work[col, col]
        for j in range(2 * n):
            work[col, j] /= d
        for i in range(n):
            if i != col:
                f = work[i, col]
                if f != 0.0:
                    for j in range(2 * n):
                        work[i, j] -= f * work[col, j]
    for i in range(n):
        for j in range(n):
            out[i, j] = work[i, n + j]


@njit(cache=True, fastmath=True)
def _align_one(i, g1, gx, gy, g2, x1, x2, r, max_iters, tol, min_norm, ux, uy,
               tmpl, img, jac, hess, hess_inv, work, A, t, b, dp, t_out, A_out, zncc, converged):
    """Align match i (see :func:`_align_kernel`); every array argument after uy is scratch or
    output, so nothing is allocated here."""
    npx = tmpl.shape[0]
    h1, w1 = g1.shape
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = 1.0, 0.0, 0.0, 1.0
    A_out[i] = A
    if not (r <= x1[i, 0] <= w1 - 1 - r and r <= x1[i, 1] <= h1 - 1 - r):
        return
    t[0], t[1] = x1[i, 0], x1[i, 1]
    tnorm, _ = _sample_normalised(g1, A, t, r, tmpl)
    if not tnorm > min_norm:
        return
    for p in range(npx):
        tmpl[p] /= tnorm
    # Jacobian of the normalised template w.r.t. (tx, ty, a11, a12, a21, a22) at identity
    for p in range(npx):
        jx = sample_bilinear(gx, x1[i, 0] + ux[p], x1[i, 1] + uy[p]) / tnorm
        jy = sample_bilinear(gy, x1[i, 0] + ux[p], x1[i, 1] + uy[p]) / tnorm
        jac[0, p] = jx
        jac[1, p] = jy
        jac[2, p] = jx * ux[p]
        jac[3, p] = jx * uy[p]
        jac[4, p] = jy * ux[p]
        jac[5, p] = jy * uy[p]
    for c in range(6):
        mean = 0.0
        for p in range(npx):
            mean += jac[c, p]
        mean /= npx
        for p in range(npx):
            jac[c, p] -= mean
    for c in range(6):
        for q in range(c, 6):
            acc = 0.0
            for p in range(npx):
                acc += jac[c, p] * jac[q, p]
            hess[c, q] = acc
            hess[q, c] = acc
    # damping of the linear part: the corner of a square leaves A undetermined along its edges
    lam = 0.01 * (hess[2, 2] + hess[3, 3] + hess[4, 4] + hess[5, 5]) / 4.0
    for c in range(2, 6):
        hess[c, c] += lam
    tiny = 1e-9 * (hess[0, 0] + hess[1, 1] + hess[2, 2] + hess[3, 3] + hess[4, 4] + hess[5, 5]) + 1e-12
    for c in range(6):
        hess[c, c] += tiny
    _invert(hess, hess_inv, work)
    det_t = hess[0, 0] * hess[1, 1] - hess[0, 1] * hess[1, 0]
    ht00, ht01, ht10, ht11 = hess[1, 1] / det_t, -hess[0, 1] / det_t, -hess[1, 0] / det_t, hess[0, 0] / det_t
    a11, a12, a21, a22 = 1.0, 0.0, 0.0, 1.0
    tx, ty = x2[i, 0], x2[i, 1]
    ok = True
    for it in range(max_iters):
        A[0, 0], A[0, 1], A[1, 0], A[1, 1] = a11, a12, a21, a22
        t[0], t[1] = tx, ty
        norm, _ = _sample_normalised(g2, A, t, r, img)
        inv_norm = 1.0 / max(norm, 1e-12)
        for p in range(npx):
            img[p] = img[p] * inv_norm - tmpl[p]  # the residual
        for c in range(6):
            acc = 0.0
            for p in range(npx):
                acc += jac[c, p] * img[p]
            b[c] = acc
        if it < 3:  # translation first
            for c in range(6):
                dp[c] = 0.0
            dp[0] = ht00 * b[0] + ht01 * b[1]
            dp[1] = ht10 * b[0] + ht11 * b[1]
        else:
            for c in range(6):
                acc = 0.0
                for q in range(6):
                    acc += hess_inv[c, q] * b[q]
                dp[c] = acc
        cap_t = 1.0 / max(max(abs(dp[0]), abs(dp[1])), 1e-12)
        cap_a = 0.1 / max(max(max(abs(dp[2]), abs(dp[3])), max(abs(dp[4]), abs(dp[5]))), 1e-12)
        scale = min(min(cap_t, cap_a), 1.0)
        # inverse composition: W <- W o W(dp)^-1, W(dp): u -> (I + D) u + d
        d11, d12, d21, d22 = 1.0 + dp[2] * scale, dp[3] * scale, dp[4] * scale, 1.0 + dp[5] * scale
        det_d = d11 * d22 - d12 * d21
        i11, i12, i21, i22 = d22 / det_d, -d12 / det_d, -d21 / det_d, d11 / det_d
        n11 = a11 * i11 + a12 * i21
        n12 = a11 * i12 + a12 * i22
        n21 = a21 * i11 + a22 * i21
        n22 = a21 * i12 + a22 * i22
        a11, a12, a21, a22 = n11, n12, n21, n22
        ntx = tx - (a11 * dp[0] + a12 * dp[1]) * scale
        nty = ty - (a21 * dp[0] + a22 * dp[1]) * scale
        moved = max(abs(ntx - tx), abs(nty - ty))
        tx, ty = ntx, nty
        f = a11 * a11 + a12 * a12 + a21 * a21 + a22 * a22
        det = a11 * a22 - a12 * a21
        disc = np.sqrt(max(f * f - 4.0 * det * det, 0.0))
        s_max, s_min = np.sqrt((f + disc) / 2.0), np.sqrt(max((f - disc) / 2.0, 0.0))
        if (s_max > 4.0 or s_min < 0.25 or max(abs(tx - x2[i, 0]), abs(ty - x2[i, 1])) > r
                or not (np.isfinite(tx) and np.isfinite(ty))):
            ok = False
            break
        if moved <= tol and it >= 3:
            break
    A[0, 0], A[0, 1], A[1, 0], A[1, 1] = a11, a12, a21, a22
    t[0], t[1] = tx, ty
    if not ok:
        return
    norm, inside = _sample_normalised(g2, A, t, r, img)
    if not inside or not norm > min_norm:
        return
    z = 0.0
    for p in range(npx):
        z += img[p] * tmpl[p]
    zncc[i] = z / max(norm, 1e-12)
    converged[i] = True
    t_out[i, 0] = tx
    t_out[i, 1] = ty
    A_out[i] = A


@njit(cache=True, fastmath=True)
def _align_kernel(g1, gx, gy, g2, x1, x2, r, max_iters, tol, min_norm):
    """Inverse-compositional affine Lucas-Kanade for every match; see :func:`align_matches`.
    The scratch arrays are made once: the per-match work allocates nothing. (A threaded version
    measured 2x faster alone but no faster in the pipeline: its threads and OpenBLAS's compete
    for the two cores.)"""
    m = x1.shape[0]
    npx = (2 * r + 1) ** 2
    t_out = x2.copy()
    A_out = np.zeros((m, 2, 2))
    zncc = np.full(m, -1.0)
    converged = np.zeros(m, np.bool_)
    ux = np.empty(npx)
    uy = np.empty(npx)
    k = 0
    for iy in range(-r, r + 1):
        for ix in range(-r, r + 1):
            ux[k] = ix
            uy[k] = iy
            k += 1
    tmpl = np.empty(npx)
    img = np.empty(npx)
    jac = np.empty((6, npx))  # one row per parameter: the sums over pixels run contiguously
    hess = np.empty((6, 6))
    hess_inv = np.empty((6, 6))
    work = np.empty((6, 12))
    A = np.empty((2, 2))
    t = np.empty(2)
    b = np.empty(6)
    dp = np.empty(6)
    for i in range(m):
        _align_one(i, g1, gx, gy, g2, x1, x2, r, max_iters, tol, min_norm, ux, uy,
                   tmpl, img, jac, hess, hess_inv, work, A, t, b, dp, t_out, A_out, zncc, converged)
    return t_out, A_out, zncc, converged


def align_matches(
    f1: Features,
    f2: Features,
    matches: Matches,
    *,
    patch_size: int = DEFAULT_ALIGN_PATCH,
    max_iters: int = 30,
    tol_px: float = 0.01,
    cache: PairCache | None = None,
) -> Alignment:
    """Align the patch of every match by affine Lucas-Kanade on normalised patches.

    For each match the (P, P) patch of image 1 centred on x1 (offsets u) is compared with image 2
    sampled at ``A u + t`` (t starting at the detected x2, A at the identity). The residual is
    the difference of the zero-mean unit-norm patches, so gain and bias changes do not matter.
    Inverse-compositional Gauss-Newton (Baker & Matthews, IJCV 2004): the Jacobian and Hessian
    come from the template once, each iteration only samples image 2. The first iterations move
    t only; every step is capped at 1 px and 0.1 of linear change (a trust region: far from the
    optimum the affine terms of the linearisation overshoot); iterations stop when t moves less
    than ``tol_px``. Needs the grey images (``Features.gray``, set by extract_features).

    Why: two Harris detections of one physical point differ by up to a few pixels once the
    viewpoint foreshortens the surface (measured: median 0.3-0.45 px, 10-20 % beyond 1 px on the
    synthetic box at 20 degrees), and the plain ZNCC of unaligned patches cannot tell. The aligned
    position is accurate to a few hundredths of a pixel, so its distance to the detected x2 says
    whether the two detections are the same point.

    Returns an :class:`Alignment` (M rows). A match does not converge if a patch leaves its
    image, is flat, or the warp degenerates (singular values outside [1/4, 4], drift beyond
    P/2 px). With a ``cache`` made for (f1, f2), pairs aligned before are not aligned again.
    """
    if f1.gray is None or f2.gray is None:
        raise StereoseedError(
            "align_matches needs the grey images: build the Features with extract_features"
        )
    params = (patch_size, max_iters, tol_px)
    if cache is not None and cache.covers(f1, f2) and cache.params in (None, params):
        cache.params = params
        stride = max(len(f2), 1)  # a pair (idx1, idx2) is coded idx1 * stride + idx2
        codes = matches.idx1.astype(np.int64) * stride + matches.idx2
        missing = np.unique(codes[cache.lookup(codes) < 0])
        if len(missing):
            todo = Matches(missing // stride, missing % stride, np.zeros(len(missing)))
            cache.add(missing, align_matches(f1, f2, todo, patch_size=patch_size, max_iters=max_iters, tol_px=tol_px))
        rows = cache.lookup(codes)
        r = cache.rows
        return Alignment(r.x2[rows], r.affine[rows], r.zncc[rows], r.converged[rows])
    x1, x2 = matches.points(f1, f2)
    g1 = np.ascontiguousarray(f1.gray, np.float32)
    g2 = np.ascontiguousarray(f2.gray, np.float32)
    gx = cv2.Sobel(g1, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g1, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    t, A, zncc, converged = _align_kernel(
        g1, gx, gy, g2, np.ascontiguousarray(x1, np.float64), np.ascontiguousarray(x2, np.float64),
        patch_size // 2, int(max_iters), float(tol_px), float(DEFAULT_MIN_PATCH_STD * patch_size))
    return Alignment(t, A, zncc, converged)


def filter_localization(
    matches: Matches,
    f1: Features,
    f2: Features,
    *,
    max_shift_px: float = DEFAULT_MAX_SHIFT_PX,
    min_zncc: float = DEFAULT_ALIGNED_MIN_ZNCC,
    patch_size: int = DEFAULT_ALIGN_PATCH,
    cache: PairCache | None = None,
) -> Matches:
    """Keep the matches whose two detections are the same point, scored by aligned ZNCC.

    Aligns every match (:func:`align_matches`) and keeps those that converged, whose aligned
    position lies within ``max_shift_px`` of the detected point of image 2, and whose aligned
    ZNCC exceeds ``min_zncc``. The kept matches' score becomes the aligned ZNCC.
    """
    if len(matches) == 0:
        return matches
    al = align_matches(f1, f2, matches, patch_size=patch_size, cache=cache)
    keep = al.converged & (al.shift(f2, matches) <= max_shift_px) & (al.zncc > min_zncc)
    return Matches(matches.idx1[keep], matches.idx2[keep], al.zncc[keep]).sorted_by_score()


def refine_features(
    f1: Features,
    f2: Features,
    matches: Matches,
    *,
    patch_size: int = DEFAULT_ALIGN_PATCH,
    cache: PairCache | None = None,
) -> Features:
    """Copy of ``f2`` whose matched points sit where their partners of image 1 are, sub-pixel.

    Each matched point of image 2 moves to the aligned position of its partner
    (:func:`align_matches`; a few hundredths of a pixel on the synthetic box, against ~0.3 px for
    independent detections); its descriptor is recomputed there. Points that are unmatched,
    matched more than once, or whose alignment did not converge keep their detected position.
    Indices are unchanged, so ``matches`` stays valid for the returned features.

    Why: triangulation and resection then see consistent positions, and a track followed pair
    after pair (a -> b -> c, refining b's features against a, then c's against b) carries the
    position of the same physical point instead of accumulating detector noise.
    """
    if len(matches) == 0:
        return f2
    al = align_matches(f1, f2, matches, patch_size=patch_size, cache=cache)
    counts = np.bincount(matches.idx2, minlength=len(f2))
    move = al.converged & (counts[matches.idx2] == 1)
    points = f2.points.copy()
    points[matches.idx2[move]] = al.x2[move]
    desc, valid = f2.desc.copy(), f2.valid.copy()
    if f2.gray is not None and move.any():
        idx = matches.idx2[move]
        desc[idx], valid[idx] = describe(f2.gray, points[idx], f2.patch_size)
    return Features(points, desc, valid, f2.response, f2.image_shape, f2.gray)


def filter_epipolar(
    matches: Matches,
    kp1: Features | np.ndarray,
    kp2: Features | np.ndarray,
    F: np.ndarray,
    band_px: float,
) -> Matches:
    """Keep the matches within ``band_px`` of their epipolar lines in both images.

    F: (3, 3) with ``x2^T F x1 = 0``; kp1, kp2: Features or (N, 2) points.
    """
    if len(matches) == 0:
        return matches
    x1, x2 = matches.points(kp1, kp2)
    d = epipolar_distances(np.asarray(F, np.float64), x1, x2)
    return matches.subset(np.isfinite(d) & (d <= band_px))


def filter_fundamental_ransac(
    matches: Matches,
    kp1: Features | np.ndarray,
    kp2: Features | np.ndarray,
    config: MatchingConfig = MatchingConfig(),
    *,
    method: int = cv2.USAC_MAGSAC,
    min_inliers: int = DEFAULT_MIN_F_INLIERS,
) -> tuple[Matches, np.ndarray | None]:
    """Estimate F robustly and keep the matches consistent with it.

    method: an OpenCV robust method (``cv2.USAC_MAGSAC`` default, or ``cv2.FM_RANSAC``); threshold
    ``config.ransac_threshold_px``, confidence and iterations from ``config``; deterministic for a
    fixed ``config.seed`` (the USAC generator state, or cv2.setRNGSeed for the other
    methods); up to ``config.ransac_runs`` runs (seeds seed, seed + 1, ...) until one has
    ``config.ransac_enough_inliers``, the F with the most inliers kept. Inliers are the matches within the threshold of their epipolar lines in both
    images (:func:`stereoseed.camera.epipolar_distances`), recomputed from the returned F.
    Returns (inlier Matches, F (3, 3) float64 of unit norm) or, with a RuntimeWarning, (empty
    Matches, None) when there are fewer than 8 matches, no estimate, or fewer than
    ``min_inliers`` inliers.
    """
    if len(matches) < 8:
        _warn(f"robust F needs at least 8 matches, got {len(matches)}")
        return Matches.empty(), None
    x1, x2 = matches.points(kp1, kp2)
    # One robust run on a weak pair (a few dozen inliers among many candidates) depends on its
    # random samples: templeSparseRing's turned 14 -> 2 pair keeps 18 to 31 matches by seed.
    # The best-supported of a few runs takes most of the luck out; a pair whose best run
    # already has many inliers is not weak and needs no more.
    F, inl, error = None, np.zeros(len(matches), bool), None
    for run in range(max(int(config.ransac_runs), 1)):
        if inl.sum() >= config.ransac_enough_inliers:
            break
        try:
            F_run = _robust_fundamental(x1, x2, config, method, int(config.seed) + run)
        except cv2.error as exc:  # degenerate configurations make some estimators throw
            error = exc
            continue
        if F_run is None or F_run.shape[0] < 3 or not np.all(np.isfinite(F_run)) or np.linalg.norm(F_run[:3]) == 0:
            continue
        F_run = np.asarray(F_run[:3], np.float64) / np.linalg.norm(F_run[:3])
        d = epipolar_distances(F_run, x1, x2)
        inl_run = np.isfinite(d) & (d <= config.ransac_threshold_px)
        if F is None or inl_run.sum() > inl.sum():
            F, inl = F_run, inl_run
    if F is None:
        _warn(f"robust F failed: {error}" if error is not None else "robust F found no model")
        return Matches.empty(), None
    if inl.sum() < min_inliers:
        _warn(f"robust F has only {int(inl.sum())} inliers (< {min_inliers}): rejected")
        return Matches.empty(), None
    return matches.subset(inl), F


def _robust_fundamental(x1: np.ndarray, x2: np.ndarray, config: MatchingConfig, method: int,
                        seed: int) -> np.ndarray | None:
    """One OpenCV robust F estimate from pixels x1, x2 (N, 2), its randomness fixed by seed."""
    if method == cv2.USAC_MAGSAC:
        # The USAC flags ignore cv2.setRNGSeed (their generator state defaults to 0); the
        # parameter object is the USAC_MAGSAC preset with the seed made explicit.
        params = cv2.UsacParams()
        params.threshold = float(config.ransac_threshold_px)
        params.confidence = float(config.ransac_confidence)
        params.maxIterations = int(config.ransac_max_iters)
        params.sampler = cv2.SAMPLING_UNIFORM
        params.score = cv2.SCORE_METHOD_MAGSAC
        params.loMethod = cv2.LOCAL_OPTIM_SIGMA
        params.final_polisher = cv2.MAGSAC
        params.randomGeneratorState = seed
        return cv2.findFundamentalMat(x1, x2, params)[0]
    cv2.setRNGSeed(seed)
    return cv2.findFundamentalMat(x1, x2, method, float(config.ransac_threshold_px),
                                  float(config.ransac_confidence), int(config.ransac_max_iters))[0]


def match_pair(
    f1: Features,
    f2: Features,
    config: MatchingConfig = MatchingConfig(),
    F: np.ndarray | None = None,
    image_width: float | None = None,
    *,
    min_zncc: float | None = DEFAULT_CANDIDATE_MIN_ZNCC,
    max_ratio: float | None = DEFAULT_GUIDED_MAX_RATIO,
    first_pass_ratio: float | None = None,
    scales: tuple[float, ...] = DEFAULT_SCALES,
    localize: bool = True,
    max_shift_px: float = DEFAULT_MAX_SHIFT_PX,
    min_aligned_zncc: float = DEFAULT_ALIGNED_MIN_ZNCC,
    align_patch_size: int = DEFAULT_ALIGN_PATCH,
    guided: bool = True,
    return_F: bool = False,
    return_stats: bool = False,
    pair_cache: PairCache | None = None,
) -> Matches | tuple:
    """Match two images: ZNCC candidates, epipolar geometry, localisation check.

    f1, f2: features of the two images (from :func:`stereoseed.features.extract_features`, which
    keeps the grey images the localisation check needs).

    * F (3, 3) known (both cameras calibrated): ZNCC candidates restricted to the
      ``config.epipolar_band_px`` band *before* the best one is chosen (guided matching), then
      the localisation check.
    * F unknown: ZNCC candidates in the search window, localisation check, robust F
      (:func:`filter_fundamental_ransac`), then, if ``guided``, a second pass guided by the
      ``config.ransac_threshold_px`` band of that F (checked again; kept if it has at least as
      many matches as the RANSAC inliers). The first pass has no uniqueness test by default
      (``first_pass_ratio`` None): the localisation check and RANSAC reject its wrong matches,
      while a ratio test there starves RANSAC (measured on the noisy 14-view ring: ratio 0.9
      left one pair with 14 inliers and no F; without it every pair has >= 47 inliers, and the
      plain box is still refused).

    Candidates (:func:`match_zncc`; ``image_width`` scales ``config.search_radius``): best ZNCC
    above ``min_zncc``, mutual if ``config.mutual``, uniqueness ratio ``max_ratio`` (None: off),
    image-2 patches also resampled at ``scales`` (zoom). The default ``min_zncc`` 0.6 deliberately
    overrides ``config.min_zncc`` (the paper's 0.8, still what :func:`match_zncc` uses): the
    localisation check below is the acceptance test here. Pass None to use the config's value.
    Localisation check (``localize``; :func:`filter_localization`): affine
    alignment of the two patches, aligned position within ``max_shift_px`` of the detected point,
    aligned ZNCC > ``min_aligned_zncc``; the kept matches are scored by their aligned ZNCC. It
    replaces the paper's single 0.8 threshold on unaligned patches, which measured on the
    synthetic box both loses most true matches under foreshortening and keeps 10-20 % of matches
    between detections more than 1 px apart. Skipped with a warning without grey images.

    Returns Matches (best score first); with ``return_F`` also the F used or estimated (None
    when the robust estimate failed: the Matches are then empty and a warning says why); with
    ``return_stats`` also a JSON-able dict of counts per stage ("features", "candidates",
    "localized", "ransac_inliers", "guided_candidates", "kept") and "geometry". Order:
    ``m``, ``(m, F)``, ``(m, stats)`` or ``(m, F, stats)``. ``pair_cache``
    (:class:`PairCache` for (f1, f2)) spares the scores and alignments already computed
    for this pair.
    """
    cand = config if min_zncc is None else dataclasses.replace(config, min_zncc=float(min_zncc))
    if localize and (f1.gray is None or f2.gray is None):
        _warn("localisation check skipped: Features without grey images (use extract_features)")
        localize = False
    stats: dict = {"features": [len(f1), len(f2)]}

    def check(m: Matches) -> Matches:
        if not localize:
            return m
        return filter_localization(
            m, f1, f2, max_shift_px=max_shift_px, min_zncc=min_aligned_zncc,
            patch_size=align_patch_size, cache=pair_cache,
        )

    def result(m: Matches, F: np.ndarray | None):
        stats["kept"] = len(m)
        out = (m,) + ((F,) if return_F else ()) + ((stats,) if return_stats else ())
        return out[0] if len(out) == 1 else out

    if F is not None:
        F = np.asarray(F, np.float64)
        band = float(config.epipolar_band_px)
        stats["geometry"] = "known F"
        m = match_zncc(f1, f2, cand, image_width, F=F, band_px=band, max_ratio=max_ratio,
                       scales=scales, cache=pair_cache)
        stats["candidates"] = len(m)
        return result(check(filter_epipolar(m, f1, f2, F, band)), F)

    m = match_zncc(f1, f2, cand, image_width, max_ratio=first_pass_ratio, scales=scales,
                   cache=pair_cache)
    stats["candidates"] = len(m)
    m = check(m)
    stats["localized"] = len(m)
    m, F = filter_fundamental_ransac(m, f1, f2, config)
    stats["ransac_inliers"] = len(m)
    stats["geometry"] = "robust F" if F is not None else "robust F failed"
    if F is not None and guided:
        band = float(config.ransac_threshold_px)
        mg = match_zncc(f1, f2, cand, image_width, F=F, band_px=band, max_ratio=max_ratio,
                        scales=scales, cache=pair_cache)
        stats["guided_candidates"] = len(mg)
        mg = check(filter_epipolar(mg, f1, f2, F, band))
        # Guided matching should only add matches; if it does not, keep the RANSAC inliers.
        if len(mg) >= len(m):
            m = mg
    return result(m, F)


def match_turned(f1: Features, image2: np.ndarray, config: MatchingConfig = MatchingConfig(),
                 feature_config: FeatureConfig = FeatureConfig(), **kwargs) -> tuple[Matches, np.ndarray]:
    """Match ``f1`` against ``image2`` turned by 180 degrees (a camera held upside down relative
    to the first: ZNCC is not rotation invariant). kwargs go to :func:`match_pair`.

    Returns (Matches into the turned image's features, (M, 2) float64 matched points of image 2
    in its own frame: x -> (W - 1 - x, H - 1 - y) with pixel (0, 0) the top-left pixel's centre).
    """
    turned = cv2.rotate(np.asarray(image2), cv2.ROTATE_180)
    f2 = extract_features(turned, feature_config, patch_size=f1.patch_size)
    m = match_pair(f1, f2, config, **kwargs)
    h, w = turned.shape[:2]
    return m, np.array([w - 1.0, h - 1.0]) - f2.points[m.idx2]


def _first_by_key(key: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Positions of the best-scoring entry of each distinct key: (M,) -> (U,) int64."""
    order = np.argsort(-score, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    return order[first]


def chain(m_ab: Matches, m_bc: Matches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of image b matched both in a (``m_ab``) and in c (``m_bc``): the paper's B_{k-1}.

    Returns (ia, ib, ic), three (K,) int64 arrays: feature ``ib[k]`` of image b is matched to
    ``ia[k]`` of a and ``ic[k]`` of c; sorted by ib. If a point of b appears in several matches
    of one set (non-mutual matching), its best-scoring match is used. O(M log M), no Python loop.
    """
    if len(m_ab) == 0 or len(m_bc) == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty.copy(), empty.copy()
    ab = _first_by_key(m_ab.idx2, m_ab.score)
    bc = _first_by_key(m_bc.idx1, m_bc.score)
    # Lookup table from a feature index of b to its position in m_bc (-1: not matched in c).
    size = int(max(m_ab.idx2[ab].max(), m_bc.idx1[bc].max())) + 1
    pos_bc = np.full(size, -1, np.int64)
    pos_bc[m_bc.idx1[bc]] = bc
    ib_all = m_ab.idx2[ab]
    hit = pos_bc[ib_all] >= 0
    ab = ab[hit]
    ib = m_ab.idx2[ab]
    order = np.argsort(ib, kind="stable")
    ab, ib = ab[order], ib[order]
    return m_ab.idx1[ab], ib, m_bc.idx2[pos_bc[ib]]


def _to_bgr_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        f = np.nan_to_num(img.astype(np.float64))
        scale = 255.0 if f.size and f.max() <= 1.0 else 1.0  # [0, 1] floats or 0..255 values
        img = np.clip(f * scale, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def draw_matches(
    img1: np.ndarray,
    kp1: Features | np.ndarray,
    img2: np.ndarray,
    kp2: Features | np.ndarray,
    matches: Matches,
    path: str | Path | None = None,
    *,
    max_lines: int | None = None,
) -> np.ndarray:
    """Side-by-side image with a line per match (paper Fig. 10b), written as PNG if ``path``.

    img1, img2: grey or BGR images (uint8 or float in [0, 1]); kp1, kp2: Features or (N, 2).
    Line colour goes from red (lowest ZNCC) to green (highest). ``max_lines`` keeps the best.
    Returns the (max(H1, H2), W1 + W2, 3) uint8 BGR canvas.
    """
    a, b = _to_bgr_u8(img1), _to_bgr_u8(img2)
    h = max(a.shape[0], b.shape[0])
    canvas = np.zeros((h, a.shape[1] + b.shape[1], 3), np.uint8)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] :] = b
    m = matches.sorted_by_score()
    if max_lines is not None:
        m = m.subset(slice(0, max_lines))
    if len(m):
        x1, x2 = m.points(kp1, kp2)
        x2 = x2 + np.array([a.shape[1], 0.0])
        lo, hi = float(m.score.min()), float(m.score.max())
        t = (m.score - lo) / (hi - lo) if hi > lo else np.ones(len(m))
        shift = 4  # draw at 1/16 px so sub-pixel positions are honoured
        p1 = np.round(x1 * (1 << shift)).astype(np.int64)
        p2 = np.round(x2 * (1 << shift)).astype(np.int64)
        # Draw the weakest first so the best matches stay on top.
        for k in np.argsort(m.score):
            colour = (0, int(255 * t[k]), int(255 * (1 - t[k])))
            q1 = (int(p1[k, 0]), int(p1[k, 1]))
            q2 = (int(p2[k, 0]), int(p2[k, 1]))
            cv2.line(canvas, q1, q2, colour, 1, cv2.LINE_AA, shift)
            cv2.circle(canvas, q1, 2 << shift, colour, 1, cv2.LINE_AA, shift)
            cv2.circle(canvas, q2, 2 << shift, colour, 1, cv2.LINE_AA, shift)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), canvas):
            raise StereoseedError(f"could not write {path}")
    return canvas
