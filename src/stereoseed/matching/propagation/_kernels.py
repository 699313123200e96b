"""Numba kernels of the match propagation (Lhuillier & Quan, PAMI 2002): per-pixel window
statistics, the ZNCC of integer pixel pairs, a max-heap and the best-first propagation itself.

Images are (H, W) float64 grey levels in [0, 1] indexed ``img[y, x]``; ``half`` is the ZNCC
window's half-size (2 for LQ02's 5x5). The algorithm is described in :mod:`stereoseed.matching.propagation.core`.
"""
from __future__ import annotations

import numpy as np
from numba import njit

# Only re-association (and fused multiply-add) is allowed: enough to vectorise the 25-term
# window sums; the "no NaN" flag stays off because the refinement tests for NaN.
FASTMATH = {"reassoc", "contract"}


@njit(cache=True, nogil=True)
def window_stats(img, half):
    """Per-pixel window mean and inverse norm.

    img: (H, W) float64; half: window half-size. Returns mean (H, W) float64 and inv_norm
    (H, W) float64 = 1 / sqrt(sum_w (I - mean)^2), 0 where the window leaves the image or is
    flat (ZNCC undefined). Two passes per pixel (mean, then centred squares) avoid the
    cancellation of sum(I^2) - n mean^2 on nearly flat windows.
    """
    H, W = img.shape
    n = (2 * half + 1) * (2 * half + 1)
    mean = np.zeros((H, W))
    inv = np.zeros((H, W))
    for y in range(half, H - half):
        for x in range(half, W - half):
            s = 0.0
            for wy in range(-half, half + 1):
                for wx in range(-half, half + 1):
                    s += img[y + wy, x + wx]
            m = s / n
            ss = 0.0
            for wy in range(-half, half + 1):
                for wx in range(-half, half + 1):
                    d = img[y + wy, x + wx] - m
                    ss += d * d
            mean[y, x] = m
            # 1e-12 ~ a window whose pixels differ by ~2e-7: numerically flat, not texture
            if ss > 1e-12:
                inv[y, x] = 1.0 / np.sqrt(ss)
    return mean, inv


@njit(cache=True)
def load_centred(img, mean, x, y, half, buf):
    """Copy the window of (x, y) minus its mean into buf ((2*half+1)^2,) float64."""
    m = mean[y, x]
    k = 0
    for wy in range(-half, half + 1):
        for wx in range(-half, half + 1):
            buf[k] = img[y + wy, x + wx] - m
            k += 1


@njit(cache=True, fastmath=FASTMATH)
def dot_window(buf, img, x, y, half):
    """sum_w buf * I(window of (x, y)). Since buf sums to zero this equals the centred product,
    so image 2 needs no mean: ZNCC = inv1 * inv2 * dot_window(...)."""
    s = 0.0
    k = 0
    for wy in range(-half, half + 1):
        for wx in range(-half, half + 1):
            s += buf[k] * img[y + wy, x + wx]
            k += 1
    return s


@njit(cache=True, nogil=True)
def zncc_points(I1, mean1, inv1, I2, inv2, pts, half):
    """ZNCC of integer pairs pts (N, 4) int64 (x1, y1, x2, y2); -1 where a window is invalid."""
    H1, W1 = I1.shape
    H2, W2 = I2.shape
    out = np.full(pts.shape[0], -1.0)
    buf = np.empty((2 * half + 1) * (2 * half + 1))
    for i in range(pts.shape[0]):
        x1, y1, x2, y2 = pts[i, 0], pts[i, 1], pts[i, 2], pts[i, 3]
        if x1 < 0 or y1 < 0 or x1 >= W1 or y1 >= H1 or x2 < 0 or y2 < 0 or x2 >= W2 or y2 >= H2:
            continue
        if inv1[y1, x1] == 0.0 or inv2[y2, x2] == 0.0:
            continue
        load_centred(I1, mean1, x1, y1, half, buf)
        out[i] = inv1[y1, x1] * inv2[y2, x2] * dot_window(buf, I2, x2, y2, half)
    return out


@njit(cache=True)
def _heap_push(hs, hi, n, score, idx):
    """Push (score, idx) on the max-heap stored in hs (float64) / hi (int32) of size n."""
    j = n
    while j > 0:
        p = (j - 1) >> 1
        if hs[p] >= score:
            break
        hs[j] = hs[p]
        hi[j] = hi[p]
        j = p
    hs[j] = score
    hi[j] = idx
    return n + 1


@njit(cache=True)
def _heap_pop(hs, hi, n):
    """Remove the top of the max-heap; returns (idx of the top, new size)."""
    top = hi[0]
    n -= 1
    if n > 0:
        score = hs[n]
        idx = hi[n]
        j = 0
        while True:
            c = 2 * j + 1
            if c >= n:
                break
            if c + 1 < n and hs[c + 1] > hs[c]:
                c += 1
            if hs[c] <= score:
                break
            hs[j] = hs[c]
            hi[j] = hi[c]
            j = c
        hs[j] = score
        hi[j] = idx
    return top, n


@njit(cache=True)
def epipolar_line(F, x, y):
    """The epipolar line (a, b, c) in image 2 of pixel (x, y) of image 1, normalised so that
    a x' + b y' + c is the signed distance in pixels, and the norm it had (0 at the epipole,
    where the line is undefined and (a, b, c) are left as they are)."""
    a = F[0, 0] * x + F[0, 1] * y + F[0, 2]
    b = F[1, 0] * x + F[1, 1] * y + F[1, 2]
    c = F[2, 0] * x + F[2, 1] * y + F[2, 2]
    nrm = np.sqrt(a * a + b * b)
    if nrm > 0.0:
        a /= nrm
        b /= nrm
        c /= nrm
    return a, b, c, nrm


@njit(cache=True)
def _claim(x1, y1, x2, y2, score, m, match_x, match_y, taken2, mx1, my1, mx2, my2, msc, hs, hi, hn):
    """Record match m: pixel (x1, y1) of image 1 with (x2, y2) of image 2, both now taken, and
    push it on the heap of matches to grow from. Returns (m + 1, the heap's new size)."""
    match_x[y1, x1] = x2
    match_y[y1, x1] = y2
    taken2[y2, x2] = True
    mx1[m] = x1
    my1[m] = y1
    mx2[m] = x2
    my2[m] = y2
    msc[m] = score
    return m + 1, _heap_push(hs, hi, hn, score, m)


@njit(cache=True, nogil=True)
def propagate_kernel(I1, mean1, inv1, ok1, I2, inv2, ok2, seeds, seed_scores, min_zncc,
                      half, radius, grad, use_f, F, band):
    """Best-first propagation. See the module docstring for the algorithm.

    I1 (H1, W1), I2 (H2, W2) float64 images; mean1, inv1 (H1, W1) and inv2 (H2, W2) window
    statistics; ok1, ok2 bool "may be matched" masks (textured, full window, not flat);
    seeds (S, 4) int64 integer seeds already in the order in which they claim their pixels,
    seed_scores (S,) float64 their ZNCC; F (3, 3) float64 used when use_f.
    Returns (x1, y1, x2, y2) int32 arrays, scores float64 array (length M), n_seeds_used,
    match_x, match_y (H1, W1) int32.
    """
    H1, W1 = I1.shape
    H2, W2 = I2.shape
    cap = min(H1 * W1, H2 * W2)  # one match per pixel in each image bounds M
    mx1 = np.empty(cap, np.int32)
    my1 = np.empty(cap, np.int32)
    mx2 = np.empty(cap, np.int32)
    my2 = np.empty(cap, np.int32)
    msc = np.empty(cap, np.float64)
    match_x = np.full((H1, W1), -1, np.int32)
    match_y = np.full((H1, W1), -1, np.int32)
    taken2 = np.zeros((H2, W2), np.bool_)
    hs = np.empty(cap, np.float64)
    hi = np.empty(cap, np.int32)
    hn = 0
    m = 0

    # seeds: claim pixels in the given order; a seed whose pixel is taken is dropped
    for k in range(seeds.shape[0]):
        x1, y1, x2, y2 = seeds[k, 0], seeds[k, 1], seeds[k, 2], seeds[k, 3]
        if not seed_scores[k] > min_zncc:
            continue
        if match_x[y1, x1] >= 0 or taken2[y2, x2]:
            continue
        m, hn = _claim(x1, y1, x2, y2, seed_scores[k], m, match_x, match_y, taken2, mx1, my1, mx2, my2, msc,
                       hs, hi, hn)
    n_seeds_used = m

    side = 2 * radius + 1
    gside = 2 * grad + 1
    ncap = side * side * gside * gside
    cs = np.empty(ncap, np.float64)
    cu = np.empty(ncap, np.int32)  # candidate pixel u, packed y * W1 + x
    cv = np.empty(ncap, np.int32)  # candidate pixel u', packed y * W2 + x
    order = np.empty(ncap, np.int32)
    buf = np.empty((2 * half + 1) * (2 * half + 1))

    while hn > 0:
        top, hn = _heap_pop(hs, hi, hn)
        x = mx1[top]
        y = my1[top]
        dx = mx2[top] - x
        dy = my2[top] - y
        nc = 0
        for vy in range(-radius, radius + 1):
            uy = y + vy
            if uy < 0 or uy >= H1:
                continue
            for vx in range(-radius, radius + 1):
                ux = x + vx
                if ux < 0 or ux >= W1:
                    continue
                # ok1 is False on the border, on flat windows and on untextured pixels
                if not ok1[uy, ux] or match_x[uy, ux] >= 0:
                    continue
                a = 0.0
                b = 0.0
                c = 0.0
                if use_f:
                    a, b, c, nrm = epipolar_line(F, ux, uy)
                    if not nrm > 0.0:  # u is the epipole: every u' is on its (undefined) line
                        a = 0.0
                        b = 0.0
                        c = 0.0
                loaded = False
                iu = inv1[uy, ux]
                for ey in range(-grad, grad + 1):
                    vy2 = uy + dy + ey
                    if vy2 < 0 or vy2 >= H2:
                        continue
                    for ex in range(-grad, grad + 1):
                        vx2 = ux + dx + ex
                        if vx2 < 0 or vx2 >= W2:
                            continue
                        if not ok2[vy2, vx2] or taken2[vy2, vx2]:
                            continue
                        if use_f and abs(a * vx2 + b * vy2 + c) > band:
                            continue
                        if not loaded:  # centre the window of u once for its <= 9 u'
                            load_centred(I1, mean1, ux, uy, half, buf)
                            loaded = True
                        z = iu * inv2[vy2, vx2] * dot_window(buf, I2, vx2, vy2, half)
                        if z > min_zncc:
                            cs[nc] = z
                            cu[nc] = uy * W1 + ux
                            cv[nc] = vy2 * W2 + vx2
                            nc += 1
        if nc == 0:
            continue
        # insertion sort of the candidate indices by decreasing ZNCC (nc <= 225, usually few)
        for i in range(nc):
            j = i
            while j > 0 and cs[order[j - 1]] < cs[i]:
                order[j] = order[j - 1]
                j -= 1
            order[j] = i
        for i in range(nc):
            k = order[i]
            uy = cu[k] // W1
            ux = cu[k] - uy * W1
            vy2 = cv[k] // W2
            vx2 = cv[k] - vy2 * W2
            if match_x[uy, ux] >= 0 or taken2[vy2, vx2]:
                continue
            m, hn = _claim(ux, uy, vx2, vy2, cs[k], m, match_x, match_y, taken2, mx1, my1, mx2, my2, msc,
                           hs, hi, hn)
    # copies: a slice would keep the arrays sized for every pixel alive (at 3072 x 2048, 150 MB
    # for a third of it used) through the sub-pixel refinement
    return (mx1[:m].copy(), my1[:m].copy(), mx2[:m].copy(), my2[:m].copy(), msc[:m].copy(), n_seeds_used,
            match_x, match_y)
