"""ZNCC matching of interest points: scores, candidate masks, mutual best, uniqueness.

Descriptors are zero-mean unit-norm patches (:mod:`stereoseed.features`), so the ZNCC of every
pair of points is a float32 matrix product and every test of :func:`match_zncc` is a mask on
that (N1, N2) matrix: candidates (search window, epipolar band), best per row and column
(mutual best), Lowe's ratio against the best competitor in both directions.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from ..config import MatchingConfig
from ..errors import StereoseedError
from ..features import Features, describe_scaled
from .containers import Matches, as_points

if TYPE_CHECKING:
    from .alignment import PairCache

__all__ = ["zncc_matrix", "candidate_mask", "match_zncc"]

log = logging.getLogger(__name__)

# float32 resolution of a ZNCC near 1 (dot product of 121 float32 terms): score differences
# below it are ties. A numerical property of the scores, not a threshold to tune.
_ZNCC_EPS = 1e-5


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
        rows = desc1[ii]
        for d2 in desc2:
            z = np.einsum("ij,ij->i", rows, d2[jj])
            np.fmax(best, z, out=best)  # fmax: NaN (unavailable) loses
        s[ii, jj] = best
        return s
    dense = zncc_matrix(desc1, desc2[0])
    for d2 in desc2[1:]:
        np.fmax(dense, zncc_matrix(desc1, d2), out=dense)
    np.copyto(dense, np.float32(-np.inf), where=~cand | np.isnan(dense))
    return dense


def candidate_mask(x1: np.ndarray, x2: np.ndarray, radius_px: float, F: np.ndarray | None = None,
                   band_px: float = np.inf) -> np.ndarray:
    """(N1, N2) bool: pairs with x2[j] (N2, 2) within ``radius_px`` of x1[i] (N1, 2) and, with F
    (3, 3), within ``band_px`` of each other's epipolar line in both images (the max of both
    one-sided distances, as :func:`stereoseed.camera.epipolar_distances`). One pass over the
    pairs, no (N1, N2) temporaries."""
    x1 = np.ascontiguousarray(x1, np.float64).reshape(-1, 2)
    x2 = np.ascontiguousarray(x2, np.float64).reshape(-1, 2)
    if F is None:  # every pair inside the band: 0 <= inf
        lines2, norm2, norm1 = np.zeros((len(x1), 3)), np.ones(len(x1)), np.ones(len(x2))
        band_px = np.inf
    else:
        F = np.asarray(F, np.float64)
        lines2 = np.hstack([x1, np.ones((len(x1), 1))]) @ F.T  # (N1, 3) epipolar lines in image 2
        lines1 = np.hstack([x2, np.ones((len(x2), 1))]) @ F  # (N2, 3) epipolar lines in image 1
        norm2 = np.hypot(lines2[:, 0], lines2[:, 1])
        norm1 = np.hypot(lines1[:, 0], lines1[:, 1])
    return _candidate_kernel(x1, x2, float(radius_px) ** 2, np.ascontiguousarray(lines2), norm2, norm1,
                             float(band_px))


@njit(cache=True, nogil=True)
def _candidate_kernel(centre, x2, radius2, lines2, norm2, norm1, band):
    """The mask of :func:`candidate_mask` from the window centres (N1, 2), the points of image 2
    (N2, 2), the epipolar lines in image 2 (N1, 3) and the normals' lengths of the lines in
    image 2 (N1,) and image 1 (N2,)."""
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


@njit(cache=True, nogil=True)
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
    """Descriptors (N2v, D) of the points ``v2`` of image 2 at scale 1 and at ``scales``: the
    moving camera's focal length varies, so the patches of image 1 are also compared with
    patches of image 2 resampled at other scales, each pair keeping its best score. NaN rows:
    not available at that scale."""
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
    config: MatchingConfig,
    image_width: float | None = None,
    *,
    F: np.ndarray | None = None,
    band_px: float | None = None,
    multiscale: bool = False,
    cache: PairCache | None = None,
) -> Matches:
    """Match two feature sets by ZNCC.

    f1, f2: features of images 1 and 2 (descriptors of the same patch size). A pair (i, j) is a
    candidate when both descriptors are valid, x2_j lies within ``config.search_radius *
    image_width`` px of x1_i (``image_width`` default: f2's image width) and, if F (3, 3) is
    given, within ``band_px`` (default ``config.epipolar_band_px``) of the epipolar lines in both
    images. With ``multiscale`` the patches of image 2 are also resampled at ``config.scales``
    (zoom between the views) and each pair keeps its best score.

    Each point of image 1 keeps its best candidate if its ZNCC exceeds ``config.min_zncc``, if it
    is also the best of the point of image 2 among its candidates (``config.mutual``), and if it
    passes the uniqueness test in both directions: ``sqrt(1 - best) < config.max_ratio *
    sqrt(1 - competitor)``, the competitor being the best other candidate farther than
    ``config.patch_size / 2`` px from the winner (closer ones sample the same structure);
    ``config.max_ratio`` None (or 1) disables it. A ``cache`` (:class:`PairCache` for (f1, f2))
    keeps the scores of all pairs for the next call on the same features.

    Returns Matches sorted by decreasing score (score: the unaligned ZNCC); empty (logged) if
    either set has no valid descriptor.
    """
    x1 = as_points(f1)
    x2 = as_points(f2)
    n1, n2 = len(x1), len(x2)
    if n1 == 0 or n2 == 0:
        log.debug("no matches: %d and %d features", n1, n2)
        return Matches.empty()
    if f1.desc.shape[1] != f2.desc.shape[1]:
        raise StereoseedError(
            f"descriptor lengths differ ({f1.desc.shape[1]} vs {f2.desc.shape[1]}): "
            "extract both feature sets with the same patch_size"
        )
    v1 = np.flatnonzero(f1.valid)
    v2 = np.flatnonzero(f2.valid)
    if len(v1) == 0 or len(v2) == 0:
        log.debug("no matches: no valid descriptor in one of the images")
        return Matches.empty()
    x1v, x2v = x1[v1], x2[v2]

    width = float(image_width if image_width is not None else f2.image_shape[1])
    radius = float(config.search_radius) * width
    band = float(config.epipolar_band_px if band_px is None else band_px)
    cand = candidate_mask(x1v, x2v, radius, F, band)

    scales = tuple(config.scales) if multiscale else ()
    if cache is not None and cache.covers(f1, f2):
        full = cache.scores.get(scales)
        if full is None:
            full = _masked_scores(f1.desc[v1], _scaled_descriptors(f2, v2, scales), np.ones(cand.shape, bool))
            cache.scores[scales] = full
        s = np.where(cand, full, np.float32(-np.inf))
    else:
        s = _masked_scores(f1.desc[v1], _scaled_descriptors(f2, v2, scales), cand)
    best2, score, best1 = _best_per_row_and_column(s)
    keep = score > config.min_zncc
    if config.mutual:
        keep &= best1[best2] == np.arange(len(v1))

    max_ratio = config.max_ratio
    if max_ratio is not None and max_ratio < 1.0:
        excl = float(config.patch_size) / 2.0
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

