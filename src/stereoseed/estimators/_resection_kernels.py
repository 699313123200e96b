"""Numba kernels of the RANSAC of :func:`stereoseed.estimators.resection.resect`.

A resection draws thousands of 6-point samples; each is a 12 x 12 DLT system whose null vector
is a hypothesis, scored by reprojecting every 3D-2D pair. Done in NumPy that is a batched SVD
and an (S, N, 3) product per batch, most of it call overhead on tiny matrices: here one compiled
pass per batch, allocation-free per sample (:func:`score_hypotheses`), and the sample drawing
loop (:func:`choose_samples`).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Inverse iterations for the DLT's null vector: each multiplies the error by the ratio of the two
# smallest eigenvalues of A^T A (small for a non-degenerate sample: noise^2 over the data's
# spread); after six, the cameras of samples that gather inliers agree with an SVD's to ~1e-12
# (measured); degenerate and nearly planar noise-free samples come out differently (an SVD's
# null vector is no better defined there)
_INVERSE_ITERATIONS = 6
# Shift making A^T A safely positive definite for its Cholesky factor (relative to its trace):
# far above the rounding of its smallest eigenvalue, far below the second smallest
_SHIFT = 1e-10


@njit(cache=True, nogil=True, error_model="numpy")
def choose_samples(rng, draws, cells, distinct_cells):
    """Samples (S, 6) int64 from candidate draws (S, C) int64: for each sample, the first draws
    that repeat neither a chosen point nor, if ``distinct_cells``, a chosen image cell (cells
    (N,) int64). A sample short of 6 (rare: C draws without 6 fitting ones) is completed by
    uniform draws of the generator ``rng`` repeating no chosen point, in sample order: the
    stream of ``rng.integers(N)`` called one at a time (Numba's Generator draws NumPy's numbers)."""
    n_samples, n_draws = draws.shape
    n = cells.shape[0]
    samples = np.zeros((n_samples, 6), np.int64)
    for s in range(n_samples):
        k = 0
        for d in range(n_draws):
            idx = draws[s, d]
            clash = False
            for q in range(k):
                if samples[s, q] == idx or (distinct_cells and cells[samples[s, q]] == cells[idx]):
                    clash = True
                    break
            if clash:
                continue
            samples[s, k] = idx
            k += 1
            if k == 6:
                break
        while k < 6:  # the weighted draws were all made before: the generator's stream goes on
            idx = rng.integers(0, n)
            fresh = True
            for q in range(k):
                if samples[s, q] == idx:
                    fresh = False
                    break
            if fresh:
                samples[s, k] = idx
                k += 1
    return samples


@njit(cache=True, nogil=True, error_model="numpy")
def _dlt_null_vector(Xn, xn, sample, A, M, L, v, w):
    """Unit null vector v (12,) of the 12 x 12 DLT system of one 6-point sample (rows as in HZ
    eq. 7.2, normalised coordinates Xn (N, 4), xn (N, 3)): the eigenvector of A^T A of the
    smallest eigenvalue, by inverse iteration on its Cholesky factor. A, M, L (12, 12) and w
    (12,) are scratch."""
    for k in range(6):
        i = sample[k]
        r0, r1 = 2 * k, 2 * k + 1
        for c in range(12):
            A[r0, c] = 0.0
            A[r1, c] = 0.0
        for c in range(4):
            A[r0, 4 + c] = -Xn[i, c]
            A[r0, 8 + c] = xn[i, 1] * Xn[i, c]
            A[r1, c] = Xn[i, c]
            A[r1, 8 + c] = -xn[i, 0] * Xn[i, c]
    trace = 0.0
    for a in range(12):
        for b in range(a, 12):
            acc = 0.0
            for r in range(12):
                acc += A[r, a] * A[r, b]
            M[a, b] = acc
            M[b, a] = acc
        trace += M[a, a]
    shift = _SHIFT * trace + 1e-300
    # Cholesky M + shift I = L L^T
    for a in range(12):
        for b in range(a + 1):
            acc = M[a, b] + (shift if a == b else 0.0)
            for q in range(b):
                acc -= L[a, q] * L[b, q]
            if a == b:
                L[a, a] = np.sqrt(max(acc, 1e-300))
            else:
                L[a, b] = acc / L[b, b]
    for a in range(12):
        v[a] = 1.0
    for _ in range(_INVERSE_ITERATIONS):
        for a in range(12):  # L w = v
            acc = v[a]
            for q in range(a):
                acc -= L[a, q] * w[q]
            w[a] = acc / L[a, a]
        norm = 0.0
        for a in range(11, -1, -1):  # L^T v = w
            acc = w[a]
            for q in range(a + 1, 12):
                acc -= L[q, a] * v[q]
            v[a] = acc / L[a, a]
            norm += v[a] * v[a]
        norm = np.sqrt(norm)
        for a in range(12):
            v[a] /= norm


@njit(cache=True, nogil=True, error_model="numpy")
def score_hypotheses(Xn, xn, samples, T_inv, U, Xh, x, threshold2):
    """The DLT camera of every sample and its inliers.

    Xn (N, 4), xn (N, 3): the normalised homogeneous pairs; samples (S, 6) int64; T_inv (3, 3),
    U (4, 4): P = T_inv Pn U undoes the normalisations; Xh (N, 4), x (N, 2): the pairs in the
    user's frame. A pair is an inlier of P when it reprojects within sqrt(threshold2) px and
    lies on the same side of P as a camera facing its points (depth sign times det P[:, :3]
    positive). Returns Ps (S, 3, 4), inliers (S, N) bool, counts (S,) int64.
    """
    n_samples, n = samples.shape[0], Xh.shape[0]
    Ps = np.empty((n_samples, 3, 4))
    inliers = np.zeros((n_samples, n), np.bool_)
    counts = np.zeros(n_samples, np.int64)
    A = np.empty((12, 12))
    M = np.empty((12, 12))
    L = np.zeros((12, 12))
    v = np.empty(12)
    w = np.empty(12)
    TP = np.empty((3, 4))
    for s in range(n_samples):
        _dlt_null_vector(Xn, xn, samples[s], A, M, L, v, w)
        for r in range(3):
            for c in range(4):
                acc = 0.0
                for q in range(3):
                    acc += T_inv[r, q] * v[4 * q + c]
                TP[r, c] = acc
        P = Ps[s]
        for r in range(3):
            for c in range(4):
                acc = 0.0
                for q in range(4):
                    acc += TP[r, q] * U[q, c]
                P[r, c] = acc
        det = (P[0, 0] * (P[1, 1] * P[2, 2] - P[1, 2] * P[2, 1])
               - P[0, 1] * (P[1, 0] * P[2, 2] - P[1, 2] * P[2, 0])
               + P[0, 2] * (P[1, 0] * P[2, 1] - P[1, 1] * P[2, 0]))
        count = 0
        for j in range(n):
            h0 = P[0, 0] * Xh[j, 0] + P[0, 1] * Xh[j, 1] + P[0, 2] * Xh[j, 2] + P[0, 3] * Xh[j, 3]
            h1 = P[1, 0] * Xh[j, 0] + P[1, 1] * Xh[j, 1] + P[1, 2] * Xh[j, 2] + P[1, 3] * Xh[j, 3]
            h2 = P[2, 0] * Xh[j, 0] + P[2, 1] * Xh[j, 1] + P[2, 2] * Xh[j, 2] + P[2, 3] * Xh[j, 3]
            if h2 * det > 0.0:  # in front (also rules out h2 = 0)
                du, dv = h0 / h2 - x[j, 0], h1 / h2 - x[j, 1]
                if du * du + dv * dv < threshold2:
                    inliers[s, j] = True
                    count += 1
        counts[s] = count
    return Ps, inliers, counts
