"""Numba kernels of ZNCC matching (:func:`stereoseed.matching.zncc.match_zncc`).

The candidates of a pair of images are a sparse set (a search window holds about a quarter of
the pairs, an epipolar band a few hundredths), kept as CSR arrays: for point i of image 1 its
candidate columns (points of image 2) are ``cols[indptr[i]:indptr[i + 1]]``, in increasing
order. Only those pairs are scored (:func:`pair_scores`), and the mutual best and the
uniqueness test run on them (:func:`best_of_pairs`, :func:`best_competitors`): nothing of size
N1 x N2 is made.
"""
from __future__ import annotations

import numpy as np
from numba import njit

# An upper bound of a ZNCC (:func:`pair_scores`) at most this far above the acceptance
# threshold cannot prune: it covers the rounding of a float32 dot product of unit vectors
# (at most n * 2^-24 ~ 1e-5 for the 121 terms of an 11 x 11 patch) with ten times to spare.
_BOUND_MARGIN = 1e-4
# Reassociation lets the dot products vectorise; not the whole of fastmath, whose "no
# infinities" would break the -inf of "no score yet"
_FAST = {"reassoc", "nsz", "contract"}


@njit(cache=True, nogil=True, inline="always")
def _candidate_row(i, centre, xs, ys, radius2, lines2, norm2, limit1, band, row):
    """row (N2,) bool: the candidates of point i of image 1 (see :func:`candidate_kernel`).
    The one place the test is written, so the dense mask and the CSR pairs agree bit for bit."""
    cx, cy = centre[i, 0], centre[i, 1]
    a, b, c = lines2[i, 0], lines2[i, 1], lines2[i, 2]
    limit2 = band * norm2[i]
    # |x2^T F x1| / norm is the distance in the image of that norm's line: the pair passes
    # when the numerator is within band times the smaller norm (no division by a zero
    # norm); without branches, so the loop vectorises
    for j in range(xs.shape[0]):
        dx, dy = xs[j] - cx, ys[j] - cy
        num = abs(a * xs[j] + b * ys[j] + c)
        row[j] = (dx * dx + dy * dy <= radius2) & (num <= limit2) & (num <= limit1[j])


@njit(cache=True, nogil=True)
def candidate_kernel(centre, x2, radius2, lines2, norm2, norm1, band):
    """The (N1, N2) bool mask of :func:`stereoseed.matching.zncc.candidate_mask` from the window
    centres (N1, 2), the points of image 2 (N2, 2), the epipolar lines in image 2 (N1, 3) and
    the normals' lengths of the lines in image 2 (N1,) and image 1 (N2,)."""
    n1, n2 = centre.shape[0], x2.shape[0]
    mask = np.empty((n1, n2), np.bool_)
    xs, ys = x2[:, 0].copy(), x2[:, 1].copy()
    limit1 = band * norm1
    for i in range(n1):
        _candidate_row(i, centre, xs, ys, radius2, lines2, norm2, limit1, band, mask[i])
    return mask


@njit(cache=True, nogil=True)
def candidate_pairs_kernel(centre, x2, radius2, lines2, norm2, norm1, band):
    """The same candidates as :func:`candidate_kernel`, as CSR arrays: indptr (N1 + 1,)
    int64 and cols (K,) int32, increasing within a row."""
    n1, n2 = centre.shape[0], x2.shape[0]
    xs, ys = x2[:, 0].copy(), x2[:, 1].copy()
    limit1 = band * norm1
    row = np.empty(n2, np.bool_)
    indptr = np.zeros(n1 + 1, np.int64)
    cols = np.empty(max(4 * n2, 64), np.int32)
    k = 0
    for i in range(n1):
        _candidate_row(i, centre, xs, ys, radius2, lines2, norm2, limit1, band, row)
        if k + n2 > cols.shape[0]:  # room for a whole row; grow by doubling
            grown = np.empty(2 * (k + n2), np.int32)
            grown[:k] = cols[:k]
            cols = grown
        for j in range(n2):  # without a branch: a third of the pairs pass, unpredictably
            cols[k] = j
            k += row[j]
        indptr[i + 1] = k
    return indptr, cols[:k].copy()


@njit(cache=True, nogil=True, fastmath=_FAST)
def pair_scores(desc1, desc2, ok2, indptr, cols, proj1, rest1, proj2, rest2, floor):
    """ZNCC of the candidate pairs, best over several descriptor sets of image 2.

    desc1: (N1, D) float32; desc2: (S, N2, D) float32, usable where ok2 (S, N2) bool; indptr
    (N1 + 1,), cols (K,): the candidates. Returns the pairs kept, as CSR (indptr (N1 + 1,),
    cols (K',) int32) with their scores (K',) float32, the max over the S sets, accumulated in
    float32 (as a BLAS sgemm does).

    floor -inf keeps every pair. Otherwise pairs scoring at most ``floor`` are dropped, and a
    set whose upper bound is below ``floor`` by :data:`_BOUND_MARGIN` is not scored at all:
    with an orthonormal basis B (L, D), a = B^T B a + q_a with q_a orthogonal to it, so
    a . b <= (B a) . (B b) + |q_a| |q_b|. proj1 (N1, L), proj2 (S, N2, L) float32 are the
    projections B a, rest1 (N1,), rest2 (S, N2) float32 the norms |q| (the bound's float32
    rounding, ~1e-6, stays far below the margin). Low image frequencies carry most of a patch,
    so the bound rules out most pairs at the cost of L << D products.
    Indices, not row views, in the loops: a view costs a reference count per pair.
    """
    n1 = indptr.shape[0] - 1
    n_sets, dim, terms = desc2.shape[0], desc1.shape[1], proj1.shape[1]
    prune = floor > -np.inf
    limit = np.float32(floor - _BOUND_MARGIN) if prune else np.float32(0.0)
    out_ptr = np.zeros(n1 + 1, np.int64)
    out_cols = np.empty(cols.shape[0], np.int32)
    out_scores = np.empty(cols.shape[0], np.float32)
    k = 0
    for i in range(n1):
        for p in range(indptr[i], indptr[i + 1]):
            j = cols[p]
            best = np.float32(-np.inf)
            for s in range(n_sets):
                if not ok2[s, j]:
                    continue
                if prune:
                    bound = rest1[i] * rest2[s, j]
                    for t in range(terms):
                        bound += proj1[i, t] * proj2[s, j, t]
                    if bound <= limit:
                        continue
                v = np.float32(0.0)
                for t in range(dim):
                    v += desc1[i, t] * desc2[s, j, t]
                if v > best:
                    best = v
            if best > floor:  # floor -inf: every pair with a usable set
                out_cols[k] = j
                out_scores[k] = best
                k += 1
        out_ptr[i + 1] = k
    return out_ptr, out_cols[:k].copy(), out_scores[:k].copy()


@njit(cache=True, nogil=True)
def best_of_pairs(indptr, cols, scores, n2):
    """Best column of each row (N1,) int64, its score (N1,) float32 (-inf without a
    candidate) and best row of each column (N2,) int64 over the CSR pairs; the first of equal
    maxima (lowest index), 0 where there is no candidate, as np.argmax of a matrix holding
    -inf elsewhere."""
    n1 = indptr.shape[0] - 1
    best_col = np.zeros(n1, np.int64)
    best_score = np.full(n1, -np.inf, np.float32)
    best_row = np.zeros(n2, np.int64)
    col_score = np.full(n2, -np.inf, np.float32)
    for i in range(n1):  # rows in increasing order: a column keeps its first best row
        for p in range(indptr[i], indptr[i + 1]):
            j = cols[p]
            v = scores[p]
            if v > best_score[i]:
                best_score[i] = v
                best_col[i] = j
            if v > col_score[j]:
                col_score[j] = v
                best_row[j] = i
    return best_col, best_score, best_row


@njit(cache=True, nogil=True)
def best_competitors(indptr, cols, scores, rows, winners, x1, x2, excl2):
    """The best competitors of the matches (rows[k], winners[k]) (K,): comp2 (K,) float32, the
    best score of row rows[k] at a column whose point lies farther than sqrt(excl2) from
    x2[winners[k]]; comp1 (K,) float32, the best score of column winners[k] at a row whose
    point lies farther than that from x1[rows[k]]. -inf without a competitor. x1 (N1, 2),
    x2 (N2, 2): the points of the rows and columns."""
    n1, n2 = indptr.shape[0] - 1, x2.shape[0]
    # the pairs by column (CSC), rows increasing within a column
    colptr = np.zeros(n2 + 1, np.int64)
    for p in range(cols.shape[0]):
        colptr[cols[p] + 1] += 1
    for j in range(n2):
        colptr[j + 1] += colptr[j]
    fill = colptr[:-1].copy()
    row_of = np.empty(cols.shape[0], np.int64)
    score_of = np.empty(cols.shape[0], np.float32)
    for i in range(n1):
        for p in range(indptr[i], indptr[i + 1]):
            j = cols[p]
            row_of[fill[j]] = i
            score_of[fill[j]] = scores[p]
            fill[j] += 1
    m = rows.shape[0]
    comp1 = np.empty(m, np.float32)
    comp2 = np.empty(m, np.float32)
    for k in range(m):
        i, w = rows[k], winners[k]
        comp2[k] = _best_beyond(indptr[i], indptr[i + 1], cols, scores, x2, x2[w, 0], x2[w, 1], excl2)
        comp1[k] = _best_beyond(colptr[w], colptr[w + 1], row_of, score_of, x1, x1[i, 0], x1[i, 1], excl2)
    return comp1, comp2


@njit(cache=True, nogil=True, inline="always")
def _best_beyond(first, end, index, score, points, cx, cy, excl2):
    """The best score[p], p in [first, end), whose point points[index[p]] lies farther than
    sqrt(excl2) from (cx, cy); -inf when there is none."""
    best = np.float32(-np.inf)
    for p in range(first, end):
        dx, dy = points[index[p], 0] - cx, points[index[p], 1] - cy
        if dx * dx + dy * dy > excl2 and score[p] > best:
            best = score[p]
    return best
