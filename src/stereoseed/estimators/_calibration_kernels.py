"""Numba kernel of :func:`stereoseed.estimators.calibration.refine_projection`: Levenberg-Marquardt on one
camera's reprojection error, compiled.

A resection polishes its hypotheses with a few hundred such refinements per run (tens of points,
up to 11 parameters, ~10 iterations each); in NumPy each iteration was some forty small array
operations. Here the whole loop runs compiled, allocation-free per iteration.

The camera is K [R | t] with K linear in the model's intrinsics (K = K_base + sum_i p_i dK_i,
:mod:`stereoseed.geometry.models`), R moved by rotation increments on the left (R <- exp([w]x) R),
t free; residuals are weighted by the Huber loss on each point's 2D error (IRLS). NumPy's
arithmetic (``error_model="numpy"``): a point on the camera's plane gives an infinite cost, as
in NumPy, not a ZeroDivisionError.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def _compose(K_base, dK, intrinsics, R, t, P):
    """P (3, 4) = K [R | t] with K = K_base + sum_i intrinsics[i] dK[i]."""
    K = K_base.copy()
    for i in range(intrinsics.shape[0]):
        for r in range(3):
            for c in range(3):
                K[r, c] += intrinsics[i] * dK[i, r, c]
    for r in range(3):
        for c in range(3):
            P[r, c] = K[r, 0] * R[0, c] + K[r, 1] * R[1, c] + K[r, 2] * R[2, c]
        P[r, 3] = K[r, 0] * t[0] + K[r, 1] * t[1] + K[r, 2] * t[2]
    return K


@njit(cache=True, nogil=True, error_model="numpy")
def _residuals(P, X, x, delta, h, r):
    """Homogeneous projections h (N, 3), residuals r (N, 2) and the Huber cost (inf when not
    finite; delta inf: the sum of squares)."""
    cost = 0.0
    for n in range(X.shape[0]):
        for k in range(3):
            h[n, k] = P[k, 0] * X[n, 0] + P[k, 1] * X[n, 1] + P[k, 2] * X[n, 2] + P[k, 3]
        r[n, 0] = h[n, 0] / h[n, 2] - x[n, 0]
        r[n, 1] = h[n, 1] / h[n, 2] - x[n, 1]
        sq = r[n, 0] * r[n, 0] + r[n, 1] * r[n, 1]
        norm = np.sqrt(sq)
        cost += sq if norm <= delta else 2.0 * delta * norm - delta * delta
    return cost if np.isfinite(cost) else np.inf


@njit(cache=True, nogil=True, error_model="numpy")
def _rotation_increment(w):
    """Rodrigues' formula for the rotation vector w (3,) (first order below 1e-12 rad, as
    :func:`stereoseed.geometry.models.rotations_from_vectors`)."""
    theta = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    if theta >= 1e-12:
        k0, k1, k2 = w[0] / theta, w[1] / theta, w[2] / theta
        s, c1 = np.sin(theta), 1.0 - np.cos(theta)
    else:
        k0, k1, k2 = w[0], w[1], w[2]
        s, c1 = 1.0, 0.0
    Kx = np.array([[0.0, -k2, k1], [k2, 0.0, -k0], [-k1, k0, 0.0]])
    out = np.eye(3) + s * Kx
    if c1 != 0.0:
        out += c1 * (Kx @ Kx)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _solve(A, b, out):
    """out = A^-1 b for a small square A by Gaussian elimination with partial pivoting; False
    when A is singular (a zero pivot)."""
    n = A.shape[0]
    M = np.empty((n, n + 1))
    for i in range(n):
        for j in range(n):
            M[i, j] = A[i, j]
        M[i, n] = b[i]
    for col in range(n):
        piv = col
        for i in range(col + 1, n):
            if abs(M[i, col]) > abs(M[piv, col]):
                piv = i
        if M[piv, col] == 0.0 or not np.isfinite(M[piv, col]):
            return False
        if piv != col:
            for j in range(n + 1):
                M[col, j], M[piv, j] = M[piv, j], M[col, j]
        for i in range(col + 1, n):
            f = M[i, col] / M[col, col]
            for j in range(col, n + 1):
                M[i, j] -= f * M[col, j]
    for i in range(n - 1, -1, -1):
        acc = M[i, n]
        for j in range(i + 1, n):
            acc -= M[i, j] * out[j]
        out[i] = acc / M[i, i]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def refine_camera(K_base, dK, intrinsics, R, t, X, x, delta, max_iterations):
    """Levenberg-Marquardt on the reprojection error of points X (N, 3) seen at x (N, 2).

    K_base (3, 3), dK (ni, 3, 3): K's constant part and its derivative along each intrinsic;
    intrinsics (ni,), R (3, 3), t (3,): the start; delta: the Huber threshold (px; inf for least
    squares). Marquardt's damping of the normal equations' diagonal, starting at 1e-3, divided
    by 10 after a step that lowers the cost and multiplied by 10 until one does; stops when a
    step gains less than 1e-10 of the cost, when none can, or after ``max_iterations``.
    Returns P (3, 4) = K [R | t] at the end (not normalised).
    """
    n_points, ni = X.shape[0], intrinsics.shape[0]
    n = ni + 6
    intrinsics = intrinsics.copy()
    R = R.copy()
    t = t.copy()
    P = np.empty((3, 4))
    h = np.empty((n_points, 3))
    r = np.empty((n_points, 2))
    K = _compose(K_base, dK, intrinsics, R, t, P)
    cost = _residuals(P, X, x, delta, h, r)
    dP = np.zeros((n, 3, 4))
    A = np.empty((n, n))
    g = np.empty(n)
    minus_g = np.empty(n)
    Ad = np.empty((n, n))
    step = np.empty(n)
    J = np.empty((2, n))
    dh = np.empty((3, n))
    P_new = np.empty((3, 4))
    h_new = np.empty((n_points, 3))
    r_new = np.empty((n_points, 2))
    intr_new = np.empty(ni)
    t_new = np.empty(3)
    damping = 1e-3
    for _ in range(max_iterations):
        if not np.isfinite(cost):
            break
        # dP/dparam: intrinsics dK_i [R | t]; rotation increments K [e_j]x R; translation K e_j
        for i in range(ni):
            for a in range(3):
                for c in range(3):
                    dP[i, a, c] = dK[i, a, 0] * R[0, c] + dK[i, a, 1] * R[1, c] + dK[i, a, 2] * R[2, c]
                dP[i, a, 3] = dK[i, a, 0] * t[0] + dK[i, a, 1] * t[1] + dK[i, a, 2] * t[2]
        for c in range(3):
            # rows of [e_j]x R: e_x -> (0, -R2, R1), e_y -> (R2, 0, -R0), e_z -> (-R1, R0, 0)
            for a in range(3):
                dP[ni, a, c] = -K[a, 1] * R[2, c] + K[a, 2] * R[1, c]
                dP[ni + 1, a, c] = K[a, 0] * R[2, c] - K[a, 2] * R[0, c]
                dP[ni + 2, a, c] = -K[a, 0] * R[1, c] + K[a, 1] * R[0, c]
        for j in range(3):
            for a in range(3):
                dP[ni + 3 + j, a, 3] = K[a, j]
        for p in range(n):
            g[p] = 0.0
            for q in range(n):
                A[p, q] = 0.0
        for m in range(n_points):
            norm = np.sqrt(r[m, 0] * r[m, 0] + r[m, 1] * r[m, 1])
            w = 1.0 if norm <= delta else delta / max(norm, 1e-300)
            inv = 1.0 / h[m, 2]
            u, v = h[m, 0] * inv, h[m, 1] * inv
            for p in range(n):
                for a in range(3):
                    dh[a, p] = (dP[p, a, 0] * X[m, 0] + dP[p, a, 1] * X[m, 1] + dP[p, a, 2] * X[m, 2]
                                + dP[p, a, 3])
                J[0, p] = (dh[0, p] - u * dh[2, p]) * inv
                J[1, p] = (dh[1, p] - v * dh[2, p]) * inv
            for p in range(n):
                g[p] += w * (J[0, p] * r[m, 0] + J[1, p] * r[m, 1])
                for q in range(p, n):
                    A[p, q] += w * (J[0, p] * J[0, q] + J[1, p] * J[1, q])
        for p in range(n):
            for q in range(p):
                A[p, q] = A[q, p]
        improved = False
        converged = False
        for p in range(n):
            minus_g[p] = -g[p]
        while damping < 1e12:
            for p in range(n):
                for q in range(n):
                    Ad[p, q] = A[p, q]
                Ad[p, p] += damping * max(A[p, p], 1e-12)
            if not _solve(Ad, minus_g, step):
                damping *= 10.0
                continue
            for i in range(ni):
                intr_new[i] = intrinsics[i] + step[i]
            R_new = _rotation_increment(step[ni:ni + 3]) @ R
            for j in range(3):
                t_new[j] = t[j] + step[ni + 3 + j]
            K_new = _compose(K_base, dK, intr_new, R_new, t_new, P_new)
            cost_new = _residuals(P_new, X, x, delta, h_new, r_new)
            if cost_new < cost:
                improved = True
                converged = cost - cost_new <= 1e-10 * cost
                intrinsics[:] = intr_new
                R = R_new
                t[:] = t_new
                K = K_new
                P[:] = P_new
                h[:] = h_new
                r[:] = r_new
                cost = cost_new
                damping = max(damping / 10.0, 1e-12)
                break
            damping *= 10.0
        if not improved or converged:
            break
    return P
