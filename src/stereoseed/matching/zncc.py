"""ZNCC matching of interest points: scores, candidates, mutual best, uniqueness.

Descriptors are zero-mean unit-norm patches (:mod:`stereoseed.features.harris`), so the ZNCC of a pair
of points is a dot product (:func:`zncc_matrix`: all of them, one float32 matrix product). The
candidates of :func:`match_zncc` (search window, epipolar band) are a small part of the N1 x N2
pairs: they are listed as CSR arrays (:func:`candidate_pairs`), only they are scored, and the
mutual best and the uniqueness test run on them (kernels in :mod:`.zncc_kernels`).
"""
from __future__ import annotations

import logging
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from stereoseed.matching.config import MatchingConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import Features, describe_scaled
from stereoseed.threads import map_chunks, split_rows
from stereoseed.matching.containers import Matches, as_points
from stereoseed.matching._zncc_kernels import best_of_pairs, candidate_kernel, candidate_pairs_kernel, best_competitors, pair_scores

if TYPE_CHECKING:
    from stereoseed.matching.alignment import PairCache

__all__ = ["zncc_matrix", "candidate_mask", "candidate_pairs", "match_zncc"]

log = logging.getLogger(__name__)

# float32 resolution of a ZNCC near 1 (dot product of 121 float32 terms): score differences
# below it are ties. A numerical property of the scores, not a threshold to tune.
_ZNCC_EPS = 1e-5
# Terms of the upper bound that spares scoring hopeless pairs (zncc_kernels.pair_scores): the
# lowest frequencies of the patch. More terms bound tighter and cost more per pair; the results
# do not depend on it.
_BOUND_TERMS = 16
# Rows of image 1 below which a thread costs more than it saves: listing a row's candidates
# takes ~2 us, scoring them ~5 us (threads.map_chunks)
_CANDIDATE_ROWS_PER_THREAD = 256
_SCORED_ROWS_PER_THREAD = 128


def zncc_matrix(desc1: np.ndarray, desc2: np.ndarray) -> np.ndarray:
    """All ZNCC scores: (N1, D) x (N2, D) zero-mean unit-norm descriptors -> (N1, N2) float32."""
    return np.asarray(desc1, np.float32) @ np.asarray(desc2, np.float32).T


def _candidate_arguments(x1: np.ndarray, x2: np.ndarray, radius_px: float, F: np.ndarray | None, band_px: float):
    """What the candidate kernels take: x1 (N1, 2), x2 (N2, 2) float64, the squared radius, the
    epipolar lines in image 2 (N1, 3), the lines' normal lengths in image 2 (N1,) and image 1
    (N2,), the band (px)."""
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
    return x1, x2, float(radius_px) ** 2, np.ascontiguousarray(lines2), norm2, norm1, float(band_px)


def candidate_mask(x1: np.ndarray, x2: np.ndarray, radius_px: float, F: np.ndarray | None = None,
                   band_px: float = np.inf) -> np.ndarray:
    """(N1, N2) bool: pairs with x2[j] (N2, 2) within ``radius_px`` of x1[i] (N1, 2) and, with F
    (3, 3), within ``band_px`` of each other's epipolar line in both images (the max of both
    one-sided distances, as :func:`stereoseed.geometry.projection.epipolar_distances`). One pass over the
    pairs, no (N1, N2) temporaries."""
    return candidate_kernel(*_candidate_arguments(x1, x2, radius_px, F, band_px))


def candidate_pairs(x1: np.ndarray, x2: np.ndarray, radius_px: float, F: np.ndarray | None = None,
                    band_px: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of :func:`candidate_mask` as CSR arrays: indptr (N1 + 1,) int64 and cols (K,)
    int32, the candidates of x1[i] being ``cols[indptr[i]:indptr[i + 1]]`` (increasing)."""
    centre, x2, radius2, lines2, norm2, norm1, band = _candidate_arguments(x1, x2, radius_px, F, band_px)
    parts = map_chunks(lambda a, b: candidate_pairs_kernel(centre[a:b], x2, radius2, lines2[a:b], norm2[a:b], norm1, band),
                       split_rows(len(centre), _CANDIDATE_ROWS_PER_THREAD))
    return _join_rows(parts)


def _join_rows(parts: list[tuple]) -> tuple:
    """One CSR matrix (indptr, then per-pair arrays) from the CSR matrices of consecutive row
    chunks (each ``(indptr, *arrays)`` with indptr starting at 0)."""
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [p[0][-1] for p in parts[:-1]])
    indptr = np.concatenate([parts[0][0][:1]] + [p[0][1:] + o for p, o in zip(parts, offsets)])
    return (indptr, *(np.concatenate(arrays) for arrays in zip(*(p[1:] for p in parts))))


@lru_cache(maxsize=8)
def _low_frequency_basis(patch_size: int) -> np.ndarray:
    """(L, P*P) float64 orthonormal rows: the 2-D DCT-II patterns of the lowest frequencies of a
    (P, P) patch, the constant one left out (descriptors are zero-mean)."""
    n = np.arange(patch_size)
    dct = np.stack([np.cos(np.pi * (n + 0.5) * k / patch_size) * np.sqrt((1.0 if k == 0 else 2.0) / patch_size)
                    for k in range(patch_size)])
    freqs = sorted((u * u + v * v, u, v) for u in range(patch_size) for v in range(patch_size))[1:]
    return np.stack([np.outer(dct[u], dct[v]).ravel() for _, u, v in freqs[:_BOUND_TERMS]])


def _bound_terms(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projections (..., L) float32 of descriptors (..., D) float32 on the low-frequency basis
    and the norms (...,) float32 of what the basis leaves out (see zncc_kernels.pair_scores).
    The norm of the residual vector itself, not sqrt(|a|^2 - |B a|^2): no cancellation where
    the basis holds almost all of a patch."""
    basis = _low_frequency_basis(int(round(np.sqrt(desc.shape[-1])))).astype(np.float32)
    flat = desc.reshape(-1, desc.shape[-1])
    proj = flat @ basis.T
    rest = np.linalg.norm(flat - proj @ basis, axis=1)
    return proj.reshape(desc.shape[:-1] + (len(basis),)), rest.reshape(desc.shape[:-1])


def _scaled_descriptors(f2: Features, v2: np.ndarray, scales: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors (S, N2v, D) float32 of the points ``v2`` of image 2 at scale 1 and at
    ``scales``, and where they are usable (S, N2v) bool: the moving camera's focal length
    varies, so the patches of image 1 are also compared with patches of image 2 resampled at
    other scales, each pair keeping its best score."""
    desc2, ok2 = [f2.desc[v2]], [np.ones(len(v2), bool)]
    if f2.gray is not None:
        for sc in scales:
            if sc != 1.0:
                d2s, ok = describe_scaled(f2.gray, f2.points[v2], f2.patch_size, sc)
                desc2.append(d2s)
                ok2.append(ok)
    return np.ascontiguousarray(np.stack(desc2), np.float32), np.stack(ok2)


def _score_pairs(f1: Features, f2: Features, v1: np.ndarray, v2: np.ndarray, scales: tuple[float, ...],
                 pairs: tuple[np.ndarray, np.ndarray], floor: float, store: dict) -> tuple:
    """Scores of the candidate ``pairs`` (CSR over v1 x v2), best over the scales; with a floor
    > -inf, the pairs scoring at most ``floor`` left out (zncc_kernels.pair_scores). ``store``
    keeps the descriptors and bound terms for the next call on the same two feature sets."""
    def kept(key, make):
        if key not in store:
            store[key] = make()
        return store[key]

    desc1 = kept(("desc1",), lambda: np.ascontiguousarray(f1.desc[v1], np.float32))
    desc2, ok2 = kept(("desc2", scales), lambda: _scaled_descriptors(f2, v2, scales))
    if floor > -np.inf:
        proj1, rest1 = kept(("bound1",), lambda: _bound_terms(desc1))
        proj2, rest2 = kept(("bound2", scales), lambda: _bound_terms(desc2))
    else:  # not read by the kernel
        proj1, rest1 = np.zeros((len(v1), 0), np.float32), np.zeros(len(v1), np.float32)
        proj2, rest2 = np.zeros(desc2.shape[:2] + (0,), np.float32), np.zeros(desc2.shape[:2], np.float32)
    indptr, cols = pairs

    def rows(a: int, b: int) -> tuple:
        return pair_scores(desc1[a:b], desc2, ok2, indptr[a:b + 1] - indptr[a], cols[indptr[a]:indptr[b]],
                            proj1[a:b], rest1[a:b], proj2, rest2, float(floor))

    return _join_rows(map_chunks(rows, split_rows(len(desc1), _SCORED_ROWS_PER_THREAD)))


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
    keeps the descriptors at the other scales and the scores of the search window without F
    for the next call on the same features.

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
    scales = tuple(config.scales) if multiscale else ()
    max_ratio = config.max_ratio
    ratio_test = max_ratio is not None and max_ratio < 1.0
    # Without the uniqueness test a pair scoring at most min_zncc can neither be kept nor beat a
    # kept pair for its column (the mutual best): such pairs need no exact score
    floor = -np.inf if ratio_test else float(config.min_zncc)
    store = cache.zncc if cache is not None and cache.covers(f1, f2) else {}
    # a search window without F is scored once per pair (robust F, then the relaxed check);
    # an epipolar band holds few pairs
    key = ("pairs", scales, radius, floor) if F is None else None
    scored = store.get(key) if key is not None else None
    if scored is None:
        scored = _score_pairs(f1, f2, v1, v2, scales, candidate_pairs(x1v, x2v, radius, F, band), floor, store)
        if key is not None:
            store[key] = scored
    indptr, cols, scores = scored
    best2, score, best1 = best_of_pairs(indptr, cols, scores, len(v2))
    keep = score > config.min_zncc
    if config.mutual:
        keep &= best1[best2] == np.arange(len(v1))

    if ratio_test:
        excl = float(config.patch_size) / 2.0
        rows = np.flatnonzero(keep)
        if len(rows):
            # Competitors in image 2 (other columns of the row) and in image 1 (other rows of
            # the column), ignoring those within excl px of the winner.
            comp1, comp2 = best_competitors(indptr, cols, scores, rows, best2[rows], x1v, x2v, excl * excl)
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

