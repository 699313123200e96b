"""Nearest points in the image plane within a radius of a few pixels: a grid search, compiled.

The pipeline asks two questions of interest points: which one lies nearest a predicted pixel,
if any lies within r (tracking, the motion prior's check), and which points of a detection
repeat an earlier one within r (one interest point per corner). A grid of square cells a
little larger than r holds every point within r of a query in the 3 x 3 cells around the
query's cell. The points are sorted by cell, row-major, so a row of three cells is one
contiguous run of the order, found by two binary searches.

scipy's cKDTree answers the same questions (the tests check it as the oracle), but loading
scipy.spatial cost every command 0.1-0.2 s of its start-up.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["nearest_within", "repeats_earlier"]

# cells a little larger than the radius: a point at exactly the radius stays in the 3 x 3 cells
# whatever the rounding of its cell coordinate
_CELL_MARGIN = 1.0 + 1e-6
# at most this many cells along an axis: any cell of at least the radius is correct, and bounded
# cell coordinates keep the int64 keys exact (a tiny radius over a wide span would overflow them)
_MAX_CELLS = 1 << 20


def _check_radius(radius: float) -> None:
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive and finite, got {radius}")


def _grid(points: np.ndarray, radius: float) -> tuple | None:
    """(origin (2,), cell size, columns, sorted cell keys (F,), order (F,)) of the F finite
    points of points (N, 2), order holding their indices in points; None when none is finite."""
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    if len(finite) == 0:
        return None
    kept = points[finite]
    origin = kept.min(axis=0)
    span = float((kept.max(axis=0) - origin).max())
    cell = max(radius * _CELL_MARGIN, span / _MAX_CELLS)
    ij = np.minimum(np.floor((kept - origin) / cell), _MAX_CELLS).astype(np.int64)
    columns = int(ij[:, 0].max()) + 1
    keys = ij[:, 1] * columns + ij[:, 0]
    order = np.argsort(keys, kind="stable")  # by cell; the kernels break distance ties by index
    return origin, cell, columns, keys[order], finite[order]


def nearest_within(points: np.ndarray, queries: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """For each query the nearest point at distance <= radius.

    points: (N, 2) float64 (a non-finite point is nobody's neighbour); queries: (M, 2) float64
    (a non-finite query has none); radius: > 0, finite, else ValueError. Returns distance (M,)
    float64, inf where no point is within radius, and index (M,) int64, N there
    (cKDTree.query's convention). Of points at the same distance the one of lowest index is
    taken.
    """
    _check_radius(radius)
    points = np.ascontiguousarray(points, np.float64).reshape(-1, 2)
    queries = np.ascontiguousarray(queries, np.float64).reshape(-1, 2)
    dist = np.full(len(queries), np.inf)
    index = np.full(len(queries), len(points), np.int64)
    grid = _grid(points, radius) if len(queries) else None
    if grid is not None:
        _nearest_kernel(points, queries, float(radius), *grid, dist, index)
    return dist, index


def repeats_earlier(points: np.ndarray, radius: float) -> np.ndarray:
    """Whether each point has a point of lower index at distance <= radius: (N,) bool.

    points: (N, 2) float64, strongest first (a non-finite point repeats none and none repeats
    it): the True ones are what keeping one point per position drops (the pairs of
    cKDTree.query_pairs(radius), the higher index of each). radius as :func:`nearest_within`'s.
    """
    _check_radius(radius)
    points = np.ascontiguousarray(points, np.float64).reshape(-1, 2)
    out = np.zeros(len(points), np.bool_)
    grid = _grid(points, radius) if len(points) > 1 else None
    if grid is not None:
        _repeats_kernel(points, float(radius), *grid, out)
    return out


@njit(cache=True, nogil=True)
def _run(keys, first_key, last_key):
    """The slice [a, b) of sorted keys holding first_key..last_key."""
    return np.searchsorted(keys, first_key), np.searchsorted(keys, last_key, side="right")


@njit(cache=True, nogil=True)
def _cell_range(value, origin, cell, count):
    """Cells value's neighbours can be in along one axis, clipped to 0..count-1: (lo, hi),
    lo > hi when none."""
    c = (value - origin) / cell
    if c < -2.0 or c > count + 1.0:  # far outside the grid (and no overflow of the integer cast below)
        return 1, 0
    i = int(np.floor(c))
    return max(i - 1, 0), min(i + 1, count - 1)


@njit(cache=True, nogil=True)
def _nearest_kernel(points, queries, radius, origin, cell, columns, keys, order, dist, index):
    rows = keys[-1] // columns + 1
    r2 = radius * radius
    for q in range(queries.shape[0]):
        qx = queries[q, 0]
        qy = queries[q, 1]
        if not (np.isfinite(qx) and np.isfinite(qy)):
            continue
        x0, x1 = _cell_range(qx, origin[0], cell, columns)
        y0, y1 = _cell_range(qy, origin[1], cell, rows)
        best = np.inf
        best_i = points.shape[0]
        for row in range(y0, y1 + 1):
            a, b = _run(keys, row * columns + x0, row * columns + x1)
            for s in range(a, b):
                i = order[s]
                dx = points[i, 0] - qx
                dy = points[i, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 <= r2 and (d2 < best or (d2 == best and i < best_i)):
                    best = d2
                    best_i = i
        if best_i < points.shape[0]:
            dist[q] = np.sqrt(best)
            index[q] = best_i


@njit(cache=True, nogil=True)
def _repeats_kernel(points, radius, origin, cell, columns, keys, order, out):
    rows = keys[-1] // columns + 1
    r2 = radius * radius
    for j in range(points.shape[0]):
        if not (np.isfinite(points[j, 0]) and np.isfinite(points[j, 1])):
            continue
        x0, x1 = _cell_range(points[j, 0], origin[0], cell, columns)
        y0, y1 = _cell_range(points[j, 1], origin[1], cell, rows)
        for row in range(y0, y1 + 1):
            a, b = _run(keys, row * columns + x0, row * columns + x1)
            for s in range(a, b):
                i = order[s]
                if i < j:
                    dx = points[i, 0] - points[j, 0]
                    dy = points[i, 1] - points[j, 1]
                    if dx * dx + dy * dy <= r2:
                        out[j] = True
                        break
            if out[j]:
                break
