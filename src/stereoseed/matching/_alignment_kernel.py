"""Numba kernels of the affine patch alignment (:func:`stereoseed.matching.alignment.align_matches`).

Inverse-compositional affine Lucas-Kanade (Baker & Matthews, IJCV 2004) on zero-mean
unit-norm patches, one match at a time, allocation-free per match: :func:`align_kernel` makes
the scratch arrays once and calls :func:`_align_one` for each match, which samples patches with
:func:`_sample_normalised` and inverts its 6x6 Hessian with :func:`_invert`.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from stereoseed.features.image import sample_bilinear

@njit(cache=True, nogil=True, fastmath=True)
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


@njit(cache=True, nogil=True, fastmath=True)
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


@njit(cache=True, nogil=True, fastmath=True)
def _align_one(i, g1, gx, gy, g2, x1, x2, r, max_iters, tol, min_norm, ux, uy,
               tmpl, img, jac, hess, hess_inv, work, A, t, b, dp, t_out, A_out, zncc, converged):
    """Align match i (see :func:`align_kernel`); every array argument after uy is scratch or
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
        # the residual and its six projections in one pass over the patch
        b0 = b1 = b2 = b3 = b4 = b5 = 0.0
        for p in range(npx):
            e = img[p] * inv_norm - tmpl[p]
            b0 += jac[0, p] * e
            b1 += jac[1, p] * e
            b2 += jac[2, p] * e
            b3 += jac[3, p] * e
            b4 += jac[4, p] * e
            b5 += jac[5, p] * e
        b[0], b[1], b[2], b[3], b[4], b[5] = b0, b1, b2, b3, b4, b5
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


@njit(cache=True, nogil=True, fastmath=True)
def align_kernel(g1, gx, gy, g2, x1, x2, r, max_iters, tol, min_norm):
    """Inverse-compositional affine Lucas-Kanade for every match (M,): images g1, gx, gy, g2
    float32, x1, x2 (M, 2), half patch side r; returns t (M, 2), A (M, 2, 2), zncc (M,),
    converged (M,) as :func:`stereoseed.matching.alignment.align_matches` describes them.
    The scratch arrays are made once: the per-match work allocates nothing. The matches are
    independent: align_matches gives chunks of them to threads (the GIL is released)."""
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
