"""Triangulation of many points at once: linear (SVD) then per-point Levenberg-Marquardt.

Paper §4.1 steps 4-5 (eq. 3-5). Every function handles N points in one batch and any number V
of views; a point need not be seen in every view (``mask``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from stereoseed.geometry.projection import camera_center, depths as camera_depths

__all__ = ["triangulate_linear", "refine_points", "TriangulationResult", "triangulate", "triangulate_two_view",
           "triangulate_tracks",
           "reprojection_errors", "triangulation_angles"]


def _as_views(Ps: np.ndarray | list, x: np.ndarray, mask: np.ndarray | None):
    Ps = np.asarray(Ps, dtype=np.float64).reshape(-1, 3, 4)
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 2:  # a single point set per view is not allowed; (V, N, 2) expected
        raise ValueError("x must have shape (V, N, 2)")
    if mask is None:
        mask = np.ones(x.shape[:2], dtype=bool)
    return Ps, x, np.asarray(mask, dtype=bool)


def triangulate_linear(Ps: np.ndarray, x: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Linear triangulation: SVD of the stacked system A M = 0 (paper eq. 3-4, HZ §12.2).

    Ps: (V, 3, 4) cameras; x: (V, N, 2) pixels; mask: (V, N) bool, which views see each point
    (each point needs >= 2). Returns (N, 3) float64. Rows are normalised so that every view
    weighs the same regardless of the scale of its P.
    """
    Ps, x, mask = _as_views(Ps, x, mask)
    V, N = mask.shape
    A = np.empty((N, 2 * V, 4))
    for v in range(V):  # V is small (2 for pairs, a track length otherwise)
        P = Ps[v] / np.linalg.norm(Ps[v][2, :3])
        rows_u = x[v, :, 0:1] * P[2] - P[0]
        rows_v = x[v, :, 1:2] * P[2] - P[1]
        w = mask[v][:, None].astype(np.float64)
        A[:, 2 * v] = rows_u * w
        A[:, 2 * v + 1] = rows_v * w
    A /= np.maximum(np.linalg.norm(A, axis=2, keepdims=True), 1e-300)
    _, _, Vt = np.linalg.svd(A)
    Mh = Vt[:, -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Mh[:, :3] / Mh[:, 3:4]


def _project_all(Ps: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous projections h (V, N, 3) and pixels (V, N, 2)."""
    h = np.einsum("vij,nj->vni", Ps[:, :, :3], X) + Ps[:, None, :, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return h, h[..., :2] / h[..., 2:3]


def reprojection_errors(Ps: np.ndarray, x: np.ndarray, X: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Reprojection distance (px) of each point in each view, NaN where not observed. -> (V, N)."""
    Ps, x, mask = _as_views(Ps, x, mask)
    _, proj = _project_all(Ps, X)
    err = np.linalg.norm(proj - x, axis=2)
    return np.where(mask, err, np.nan)


def refine_points(Ps: np.ndarray, x: np.ndarray, X0: np.ndarray, mask: np.ndarray | None = None,
                  iterations: int = 10) -> np.ndarray:
    """Per-point Levenberg-Marquardt on the reprojection error (paper eq. 5), all points at once.

    Each point has its own 3x3 normal equations and damping; points stop moving independently.
    Ps: (V, 3, 4); x: (V, N, 2); X0: (N, 3) initial points -> (N, 3).
    """
    Ps, x, mask = _as_views(Ps, x, mask)
    X = np.array(X0, dtype=np.float64, copy=True)
    ok = np.all(np.isfinite(X), axis=1)
    X[~ok] = 0.0
    w = mask.astype(np.float64)
    lam = np.full(len(X), 1e-3)

    def cost_and_jac(Xc):
        h, proj = _project_all(Ps, Xc)
        r = (proj - x) * w[..., None]  # (V, N, 2)
        # d(u)/dX = (P0 - u P2) / h2, d(v)/dX = (P1 - v P2) / h2
        inv = 1.0 / h[..., 2]
        Ju = (Ps[:, None, 0, :3] - proj[..., 0:1] * Ps[:, None, 2, :3]) * inv[..., None]
        Jv = (Ps[:, None, 1, :3] - proj[..., 1:2] * Ps[:, None, 2, :3]) * inv[..., None]
        J = np.stack([Ju, Jv], axis=2) * w[..., None, None]  # (V, N, 2, 3)
        cost = np.sum(r * r, axis=(0, 2))
        return r, J, cost

    r, J, cost = cost_and_jac(X)
    for _ in range(iterations):
        H = np.einsum("vnki,vnkj->nij", J, J)
        g = np.einsum("vnki,vnk->ni", J, r)
        Hd = H + lam[:, None, None] * np.eye(3) * (np.trace(H, axis1=1, axis2=2)[:, None, None] / 3 + 1e-12)
        try:
            step = np.linalg.solve(Hd, -g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        step[~np.all(np.isfinite(step), axis=1)] = 0.0
        Xn = X + step
        rn, Jn, cost_n = cost_and_jac(Xn)
        better = np.isfinite(cost_n) & (cost_n < cost)
        X[better] = Xn[better]
        r[:, better] = rn[:, better]
        J[:, better] = Jn[:, better]
        cost[better] = cost_n[better]
        lam = np.where(better, lam * 0.3, lam * 10.0)
    X[~ok] = np.nan
    return X


def triangulation_angles(Ps: np.ndarray, X: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Largest angle (degrees) between the rays from the observing cameras to each point. -> (N,).

    Ps: (V, 3, 4); X: (N, 3); mask: (V, N) bool (which cameras observe each point) or None (all).
    0 for a point seen by fewer than two cameras, NaN for a point at a camera centre or not finite."""
    Ps = np.asarray(Ps, dtype=np.float64).reshape(-1, 3, 4)
    X = np.ascontiguousarray(X, np.float64).reshape(-1, 3)
    mask = np.ones((len(Ps), len(X)), dtype=bool) if mask is None else np.ascontiguousarray(mask, bool)
    out = np.empty(len(X))
    _largest_angles(np.stack([camera_center(P) for P in Ps]), X, mask, out)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _largest_angles(C, X, mask, out):
    """out[i] = :func:`triangulation_angles` of point X[i] seen from the centres C (V, 3) that
    mask[:, i] selects, one pass over the points (the dense stage asks it of every match)."""
    V = C.shape[0]
    for i in range(X.shape[0]):
        best = 0.0
        for a in range(V):
            if not mask[a, i]:
                continue
            a0, a1, a2 = C[a, 0] - X[i, 0], C[a, 1] - X[i, 1], C[a, 2] - X[i, 2]
            for b in range(a + 1, V):
                if not mask[b, i]:
                    continue
                b0, b1, b2 = C[b, 0] - X[i, 0], C[b, 1] - X[i, 1], C[b, 2] - X[i, 2]
                cos = (a0 * b0 + a1 * b1 + a2 * b2) / np.sqrt((a0 * a0 + a1 * a1 + a2 * a2)
                                                              * (b0 * b0 + b1 * b1 + b2 * b2))
                if not np.isfinite(cos):  # a point at a centre or not finite: NaN, as np.maximum keeps it
                    best = np.nan
                    continue
                angle = np.degrees(np.arccos(min(1.0, max(-1.0, cos))))
                if angle > best:  # never true once best is NaN
                    best = angle
        out[i] = best


@dataclass
class TriangulationResult:
    """Triangulated points with the measures callers filter on.

    points: (N, 3); errors: (V, N) reprojection distance in px (NaN where unobserved);
    depths: (V, N) signed depth in each camera; angles: (N,) degrees.
    """

    points: np.ndarray
    errors: np.ndarray
    depths: np.ndarray
    angles: np.ndarray

    def max_error(self) -> np.ndarray:
        return np.nanmax(self.errors, axis=0)

    def valid(self, max_error_px: float, min_angle_deg: float, mask: np.ndarray | None = None) -> np.ndarray:
        """Finite, in front of every observing camera, small reprojection error, wide enough angle."""
        observed = np.isfinite(self.errors) if mask is None else mask
        in_front = np.all((self.depths > 0) | ~observed, axis=0)
        with np.errstate(invalid="ignore"):
            return (np.all(np.isfinite(self.points), axis=1) & in_front
                    & (self.max_error() <= max_error_px) & (self.angles >= min_angle_deg))


def triangulate(Ps: np.ndarray, x: np.ndarray, mask: np.ndarray | None = None, iterations: int = 10) -> TriangulationResult:
    """Linear triangulation refined by LM, with errors, depths and angles.

    Ps: (V, 3, 4); x: (V, N, 2); mask: (V, N) bool or None (all observed).
    """
    Ps, x, mask = _as_views(Ps, x, mask)
    X = refine_points(Ps, x, triangulate_linear(Ps, x, mask), mask, iterations)
    return TriangulationResult(
        points=X,
        errors=reprojection_errors(Ps, x, X, mask),
        depths=np.stack([camera_depths(P, X) for P in Ps]),
        angles=triangulation_angles(Ps, X, mask),
    )


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sums of ``values`` (O, ...) grouped by ``index`` (O,) in 0..n-1 -> (n, ...): one
    ``np.bincount`` per component (in observation order, as ``np.add.at``, at a tenth of its
    cost)."""
    flat = values.reshape(len(values), -1)
    sums = [np.bincount(index, weights=flat[:, j], minlength=n) for j in range(flat.shape[1])]
    return np.stack(sums, axis=1).reshape((n,) + values.shape[1:])


def triangulate_tracks(P_obs: np.ndarray, xy: np.ndarray, point_index: np.ndarray, n_points: int,
                       iterations: int = 10) -> np.ndarray:
    """Triangulate points seen in varying numbers of views (tracks of any length).

    P_obs: (O, 3, 4) the camera of each observation; xy: (O, 2) its pixel; point_index: (O,)
    which point (0..n_points-1) it belongs to. Linear solution from the per-point sum of the
    DLT rows' outer products (4x4, smallest eigenvector), then Gauss-Newton/LM per point with
    the normal equations accumulated over its observations (compiled: :func:`_tracks_lm`).
    Returns (n_points, 3); points with fewer than two observations are NaN.
    """
    P_obs = np.ascontiguousarray(P_obs, np.float64)
    xy = np.ascontiguousarray(xy, np.float64)
    point_index = np.asarray(point_index, np.int64)
    scale = np.linalg.norm(P_obs[:, 2, :3], axis=1)
    Pn = P_obs / scale[:, None, None]
    ru = xy[:, 0:1] * Pn[:, 2] - Pn[:, 0]
    rv = xy[:, 1:2] * Pn[:, 2] - Pn[:, 1]
    ru /= np.linalg.norm(ru, axis=1, keepdims=True)
    rv /= np.linalg.norm(rv, axis=1, keepdims=True)
    AtA = _sum_by(point_index, ru[:, :, None] * ru[:, None, :] + rv[:, :, None] * rv[:, None, :], n_points)
    _, vecs = np.linalg.eigh(AtA)
    Mh = vecs[:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Mh[:, :3] / Mh[:, 3:4]
    counts = np.bincount(point_index, minlength=n_points)
    bad = (counts < 2) | ~np.all(np.isfinite(X), axis=1)
    X[bad] = np.nan
    # each point's observations together, in their order (the sums' order is the one np.bincount had)
    order = np.argsort(point_index, kind="stable")
    starts = np.zeros(n_points + 1, np.int64)
    np.cumsum(counts, out=starts[1:])
    return _tracks_lm(P_obs, xy, order, starts, np.ascontiguousarray(X), int(iterations))


@njit(cache=True, nogil=True)
def _track_normal(P_obs, xy, order, first, last, X, H, g):
    """Normal equations H (3, 3), g (3,) of one point X (3,) over its observations
    ``order[first:last]`` (J^T J and J^T r of the reprojection residuals); returns the cost
    (sum of squared residuals)."""
    H[:, :] = 0.0
    g[:] = 0.0
    cost = 0.0
    for q in range(first, last):
        o = order[q]
        h0 = P_obs[o, 0, 0] * X[0] + P_obs[o, 0, 1] * X[1] + P_obs[o, 0, 2] * X[2] + P_obs[o, 0, 3]
        h1 = P_obs[o, 1, 0] * X[0] + P_obs[o, 1, 1] * X[1] + P_obs[o, 1, 2] * X[2] + P_obs[o, 1, 3]
        h2 = P_obs[o, 2, 0] * X[0] + P_obs[o, 2, 1] * X[1] + P_obs[o, 2, 2] * X[2] + P_obs[o, 2, 3]
        u, v = h0 / h2, h1 / h2
        r0, r1 = u - xy[o, 0], v - xy[o, 1]
        inv = 1.0 / h2
        ju0 = (P_obs[o, 0, 0] - u * P_obs[o, 2, 0]) * inv
        ju1 = (P_obs[o, 0, 1] - u * P_obs[o, 2, 1]) * inv
        ju2 = (P_obs[o, 0, 2] - u * P_obs[o, 2, 2]) * inv
        jv0 = (P_obs[o, 1, 0] - v * P_obs[o, 2, 0]) * inv
        jv1 = (P_obs[o, 1, 1] - v * P_obs[o, 2, 1]) * inv
        jv2 = (P_obs[o, 1, 2] - v * P_obs[o, 2, 2]) * inv
        H[0, 0] += ju0 * ju0 + jv0 * jv0
        H[0, 1] += ju0 * ju1 + jv0 * jv1
        H[0, 2] += ju0 * ju2 + jv0 * jv2
        H[1, 1] += ju1 * ju1 + jv1 * jv1
        H[1, 2] += ju1 * ju2 + jv1 * jv2
        H[2, 2] += ju2 * ju2 + jv2 * jv2
        g[0] += ju0 * r0 + jv0 * r1
        g[1] += ju1 * r0 + jv1 * r1
        g[2] += ju2 * r0 + jv2 * r1
        cost += r0 * r0 + r1 * r1
    H[1, 0], H[2, 0], H[2, 1] = H[0, 1], H[0, 2], H[1, 2]
    return cost


@njit(cache=True, nogil=True)
def _solve3_pivoting(A, b, x):
    """x (3,) with A x = b, A (3, 3) by Gaussian elimination with partial pivoting (A, b are
    overwritten); NaN where A is singular, as a LAPACK solve gives it."""
    for c in range(3):
        piv = c
        for r in range(c + 1, 3):
            if abs(A[r, c]) > abs(A[piv, c]):
                piv = r
        if piv != c:
            for k in range(3):
                A[c, k], A[piv, k] = A[piv, k], A[c, k]
            b[c], b[piv] = b[piv], b[c]
        if A[c, c] == 0.0:
            x[:] = np.nan
            return
        for r in range(c + 1, 3):
            f = A[r, c] / A[c, c]
            for k in range(c, 3):
                A[r, k] -= f * A[c, k]
            b[r] -= f * b[c]
    for c in range(2, -1, -1):
        acc = b[c]
        for k in range(c + 1, 3):
            acc -= A[c, k] * x[k]
        x[c] = acc / A[c, c]


@njit(cache=True, nogil=True)
def _tracks_lm(P_obs, xy, order, starts, X, iterations):
    """Levenberg-Marquardt of each point X (N, 3) on the reprojection error of its
    observations ``order[starts[p]:starts[p + 1]]`` (P_obs (O, 3, 4), xy (O, 2)): damping
    lam * (trace(H) / 3) on the diagonal, 0.3x after a step that lowers the cost, 10x after one
    that does not. Rows of X that are NaN stay NaN. Returns X refined."""
    H = np.empty((3, 3))
    g = np.empty(3)
    Hn = np.empty((3, 3))
    gn = np.empty(3)
    A = np.empty((3, 3))
    b = np.empty(3)
    step = np.empty(3)
    Xn = np.empty(3)
    for p in range(X.shape[0]):
        if not (np.isfinite(X[p, 0]) and np.isfinite(X[p, 1]) and np.isfinite(X[p, 2])):
            continue
        first, last = starts[p], starts[p + 1]
        cost = _track_normal(P_obs, xy, order, first, last, X[p], H, g)
        lam = 1e-3
        for _ in range(iterations):
            damp = lam * ((H[0, 0] + H[1, 1] + H[2, 2]) / 3 + 1e-12)
            for r in range(3):
                for c in range(3):
                    A[r, c] = (H[r, c] + damp) + 1e-15 if r == c else H[r, c]
                b[r] = -g[r]
            _solve3_pivoting(A, b, step)
            if not (np.isfinite(step[0]) and np.isfinite(step[1]) and np.isfinite(step[2])):
                step[:] = 0.0
            for k in range(3):
                Xn[k] = X[p, k] + step[k]
            cost_n = _track_normal(P_obs, xy, order, first, last, Xn, Hn, gn)
            if np.isfinite(cost_n) and cost_n < cost:
                X[p, :] = Xn
                cost = cost_n
                H[:, :] = Hn
                g[:] = gn
                lam *= 0.3
            else:
                lam *= 10.0
    return X


@njit(cache=True, nogil=True)
def _solve3(H, g):
    """Solve the 3x3 system H x = g by Cramer's rule (H symmetric positive definite here)."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 1], H[1, 2], H[2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    det = a * c00 + b * c01 + c * c02
    if abs(det) < 1e-300:
        return np.zeros(3), False
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    x = np.empty(3)
    x[0] = (c00 * g[0] + c01 * g[1] + c02 * g[2]) / det
    x[1] = (c01 * g[0] + c11 * g[1] + c12 * g[2]) / det
    x[2] = (c02 * g[0] + c12 * g[1] + c22 * g[2]) / det
    return x, True



@njit(cache=True, nogil=True, inline="always")
def _add_row(H: np.ndarray, g: np.ndarray, a0: float, a1: float, a2: float, b: float) -> None:
    """Accumulate one equation a . X = b into the normal equations (upper triangle of H)."""
    H[0, 0] += a0 * a0
    H[0, 1] += a0 * a1
    H[0, 2] += a0 * a2
    H[1, 1] += a1 * a1
    H[1, 2] += a1 * a2
    H[2, 2] += a2 * a2
    g[0] += a0 * b
    g[1] += a1 * b
    g[2] += a2 * b


@njit(cache=True, nogil=True)
def _two_view_kernel(P1, P2, x1, x2, iterations, out_X, out_err):
    n = x1.shape[0]
    H = np.empty((3, 3))
    g = np.empty(3)
    for i in range(n):
        # linear: the four DLT rows with W = 1, in least squares (normal equations)
        H[:, :] = 0.0
        g[:] = 0.0
        for v in range(2):
            P = P1 if v == 0 else P2
            x = x1[i] if v == 0 else x2[i]
            s = 1.0 / np.sqrt(P[2, 0] ** 2 + P[2, 1] ** 2 + P[2, 2] ** 2)
            for row in range(2):
                r0 = (x[row] * P[2, 0] - P[row, 0]) * s
                r1 = (x[row] * P[2, 1] - P[row, 1]) * s
                r2 = (x[row] * P[2, 2] - P[row, 2]) * s
                r3 = (x[row] * P[2, 3] - P[row, 3]) * s
                _add_row(H, g, r0, r1, r2, -r3)
        H[1, 0] = H[0, 1]
        H[2, 0] = H[0, 2]
        H[2, 1] = H[1, 2]
        X, ok = _solve3(H, g)
        if not ok:
            out_X[i, :] = np.nan
            out_err[i] = np.inf
            continue
        # Gauss-Newton on the reprojection error (eq. 5)
        for _ in range(iterations):
            H[:, :] = 0.0
            g[:] = 0.0
            for v in range(2):
                P = P1 if v == 0 else P2
                x = x1[i] if v == 0 else x2[i]
                h0 = P[0, 0] * X[0] + P[0, 1] * X[1] + P[0, 2] * X[2] + P[0, 3]
                h1 = P[1, 0] * X[0] + P[1, 1] * X[1] + P[1, 2] * X[2] + P[1, 3]
                h2 = P[2, 0] * X[0] + P[2, 1] * X[1] + P[2, 2] * X[2] + P[2, 3]
                u = h0 / h2
                w = h1 / h2
                for row in range(2):
                    val = u if row == 0 else w
                    j0 = (P[row, 0] - val * P[2, 0]) / h2
                    j1 = (P[row, 1] - val * P[2, 1]) / h2
                    j2 = (P[row, 2] - val * P[2, 2]) / h2
                    r = val - x[row]
                    _add_row(H, g, j0, j1, j2, -r)
            H[1, 0] = H[0, 1]
            H[2, 0] = H[0, 2]
            H[2, 1] = H[1, 2]
            step, ok = _solve3(H, g)
            if not ok:
                break
            X += step
        worst = 0.0
        for v in range(2):
            P = P1 if v == 0 else P2
            x = x1[i] if v == 0 else x2[i]
            h0 = P[0, 0] * X[0] + P[0, 1] * X[1] + P[0, 2] * X[2] + P[0, 3]
            h1 = P[1, 0] * X[0] + P[1, 1] * X[1] + P[1, 2] * X[2] + P[1, 3]
            h2 = P[2, 0] * X[0] + P[2, 1] * X[1] + P[2, 2] * X[2] + P[2, 3]
            e = np.sqrt((h0 / h2 - x[0]) ** 2 + (h1 / h2 - x[1]) ** 2)
            if e > worst:
                worst = e
        out_X[i, :] = X
        out_err[i] = worst


def triangulate_two_view(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray,
                         iterations: int = 3) -> TriangulationResult:
    """Many matches of one pair at once, compiled: the dense stage's hot loop.

    Same estimate as :func:`triangulate` (linear least squares, then Gauss-Newton on the
    reprojection error) without its per-batch overheads. P1, P2: (3, 4); x1, x2: (N, 2).
    Points at infinity (W = 0) are not representable here: they come out NaN or far away and
    are filtered by their angle.
    """
    P1 = np.ascontiguousarray(P1, np.float64)
    P2 = np.ascontiguousarray(P2, np.float64)
    x1 = np.ascontiguousarray(x1, np.float64)
    x2 = np.ascontiguousarray(x2, np.float64)
    X = np.empty((len(x1), 3))
    worst = np.empty(len(x1))
    _two_view_kernel(P1, P2, x1, x2, iterations, X, worst)
    errors = np.stack([worst, worst])
    return TriangulationResult(points=X, errors=errors,
                               depths=np.stack([camera_depths(P, X) for P in (P1, P2)]),
                               angles=triangulation_angles(np.stack([P1, P2]), X))

