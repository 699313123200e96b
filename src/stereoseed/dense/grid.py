"""A regular grid over a point cloud (N, 3): each point's cell, one integer key per cell
(:func:`voxel_keys`, the fusion's voxels), and the k nearest points of each point searched cell
by cell (:func:`nearest_neighbours`, the normals' neighbourhoods), a k-d tree where the grid
cannot do it."""
from __future__ import annotations

from typing import Iterator

import numpy as np
from numba import njit

from stereoseed.arrays import sort_order
from stereoseed.threads import map_chunks, split_rows

__all__ = ["voxel_keys", "nearest_neighbours", "neighbour_chunks"]


def voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    """One int64 per point (N, 3), equal for the points of one cell of side ``size``."""
    points = np.ascontiguousarray(points, np.float64)
    if not np.isfinite(points).all():  # a NaN has no cell (the compiled min skips it)
        raise ValueError("voxel keys of points that are not all finite")
    keys, fits = _cell_keys(points, float(size))
    if fits:
        return keys
    # a grid too fine for one integer key (it would wrap and merge far cells): the cells' ranks
    return np.unique(_cells(points, float(size)), axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)


@njit(cache=True, nogil=True)
def _grid_origin(points):
    """The lowest coordinate per axis (3,) of the points (N, 3): the corner of cell (0, 0, 0)."""
    low = np.full(3, np.inf)
    for i in range(points.shape[0]):
        for a in range(3):
            low[a] = min(low[a], points[i, a])
    return low


@njit(cache=True, nogil=True, inline="always")
def _cell_of(points, i, a, low, size):
    """Point i's cell index along axis a: floor((p - low) / size)."""
    return np.int64(np.floor((points[i, a] - low[a]) / size))


@njit(cache=True, nogil=True)
def _cells(points, size):
    """The cell (N, 3) int64 of each point (N, 3), counted from :func:`_grid_origin`."""
    low = _grid_origin(points)
    cells = np.empty((points.shape[0], 3), np.int64)
    for i in range(points.shape[0]):
        for a in range(3):
            cells[i, a] = _cell_of(points, i, a, low, size)
    return cells


@njit(cache=True, nogil=True)
def _cell_keys(points, size):
    """The row-major key (N,) of each point's cell (:func:`_cells`), and whether the grid's cell
    count stays below 2**62 (else the keys are not filled). In a few passes over the points,
    without the cells array: NumPy's way made five temporaries of the cloud's size (0.3 s on 2M
    points)."""
    n = points.shape[0]
    low = _grid_origin(points)
    span = np.zeros(3, np.int64)
    for i in range(n):
        for a in range(3):
            span[a] = max(span[a], _cell_of(points, i, a, low, size) + 1)
    keys = np.empty(n, np.int64)
    fits = float(span[0]) * float(span[1]) * float(span[2]) < 2.0 ** 62
    if fits:
        for i in range(n):
            keys[i] = ((_cell_of(points, i, 0, low, size) * span[1] + _cell_of(points, i, 1, low, size)) * span[2]
                       + _cell_of(points, i, 2, low, size))
    return keys, fits


# The grid search looks at most this many cells away; points with fewer neighbours that near
# (isolated stray points) are searched by a k-d tree. Its column table (one int64 per x, y cell)
# may have this many entries per point, or 2**20 (8 MB), whichever is more: a fused surface
# needs a few; a cloud spread thin over a wide grid goes to the k-d tree.
_GRID_MAX_RADIUS = 32
_GRID_COLUMNS_PER_POINT = 8


def nearest_neighbours(points: np.ndarray, k: int, cell: float | None = None) -> np.ndarray:
    """The indices (N, k) int32 of the k nearest points of each point of ``points`` (N, 3),
    finite, 1 <= k <= N (itself included), nearest first, as
    ``cKDTree(points).query(points, k)[1]`` gives them (points at exactly the same distance may
    come in another order, or another of them be taken at the k-th place).

    cell: when given, the search runs on a grid of that step (a compiled kernel that stops once
    the k-th distance is within the cells it has scanned), the points sorted by column (x, y
    cell) then z; a k-d tree finishes the points without k neighbours within
    ``_GRID_MAX_RADIUS`` cells, and does it all when the grid's column table would be too large."""
    found = np.empty((len(points), k), np.int32)
    for rows, part in neighbour_chunks(points, k, cell):
        found[rows] = part
    return found


def neighbour_chunks(points: np.ndarray, k: int, cell: float | None = None,
                     chunk: int = 1 << 20) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """:func:`nearest_neighbours`, ``chunk`` points at a time: (rows (R,) int64, their neighbours
    (R, k) int32), every point in one chunk. A caller that uses each point's neighbours once (the
    normals) never holds all of them: for a full-resolution cloud, hundreds of MB."""
    points = np.ascontiguousarray(points, np.float64)
    n = len(points)
    if not 1 <= k <= n:
        raise ValueError(f"nearest_neighbours: k = {k} neighbours of {n} points")
    tree = _Tree(points)
    if cell is not None:
        cells = _cells(points, float(cell))
        span = cells.max(axis=0) + 1
        columns = float(span[0]) * float(span[1])
        if columns * float(span[2]) < 2.0 ** 62 and columns <= max(_GRID_COLUMNS_PER_POINT * n, 1 << 20):
            column = cells[:, 0] * span[1] + cells[:, 1]
            order = sort_order(column * span[2] + cells[:, 2])
            del cells  # (a fused full-resolution cloud is millions of points: each copy counts)
            ordered = points[order]
            ordered_cells = _cells(ordered, float(cell))  # the same corner (the lowest coordinates), the same cells
            starts = np.zeros(span[0] * span[1] + 1, np.int64)
            np.cumsum(np.bincount(column, minlength=span[0] * span[1]), out=starts[1:])
            del column
            low = _grid_origin(points)
            for first in range(0, n, chunk):
                end = min(first + chunk, n)
                # int32: half the memory of the largest array of the normals (a cloud of 2**31
                # points would not fit anyway)
                found = np.empty((end - first, k), np.int32)
                map_chunks(lambda a, b: _grid_neighbours(ordered, ordered_cells, starts, order, int(span[1]),
                                                         float(cell), low, a, b, _GRID_MAX_RADIUS, found, first),
                           first + split_rows(end - first, 50_000))
                missing = np.flatnonzero(found[:, 0] < 0)
                if len(missing):
                    found[missing] = tree.query(ordered[first + missing], k)
                yield order[first:end], found
            return
    for first in range(0, n, chunk):
        rows = np.arange(first, min(first + chunk, n))
        yield rows, tree.query(points[rows], k)


class _Tree:
    """scipy's k-d tree of the points (N, 3), built at its first query (a grid search may need
    none): ``query(queries (M, 3), k)`` the indices (M, k) int32 of each query's k nearest,
    nearest first. scipy is loaded here only, where the grid search cannot do it."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        self.tree = None

    def query(self, queries: np.ndarray, k: int) -> np.ndarray:
        if self.tree is None:
            from scipy.spatial import cKDTree

            self.tree = cKDTree(self.points)
        return self.tree.query(queries, k=k, workers=-1)[1].reshape(len(queries), k).astype(np.int32)


@njit(cache=True, nogil=True)
def _grid_neighbours(points, cells, starts, order, span_y, step, low, first, end, max_radius, found, base):
    """The k = found.shape[1] nearest of points i in [first, end) of the points (N, 3) sorted by
    column (x cell * span_y + y cell) then z cell (cells (N, 3), of side step from the corner
    low (3,)); starts (C + 1,) the first row of each column; order (N,) each sorted point's
    index in the caller's order, which found (R, k) gives; point i's are its row i - base. The cells are scanned in
    growing cubes of radius r around the point's own; after the cube of radius r every point
    left out is at least r * step + (the point's distance to its own cell's nearest face) away,
    so the search stops once the k-th distance is within that. -1 in found's first column: not
    within max_radius cells."""
    k = found.shape[1]
    n_x = (starts.shape[0] - 1) // span_y
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    for i in range(first, end):
        cx, cy, cz = cells[i, 0], cells[i, 1], cells[i, 2]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        face = max(min(px - (low[0] + cx * step), low[0] + (cx + 1) * step - px,
                       py - (low[1] + cy * step), low[1] + (cy + 1) * step - py,
                       pz - (low[2] + cz * step), low[2] + (cz + 1) * step - pz), 0.0)
        count = 0
        scanned = -1  # the cube of this radius is in best already
        done = False
        r = 1
        while True:
            for x in range(max(cx - r, 0), min(cx + r, n_x - 1) + 1):
                for y in range(max(cy - r, 0), min(cy + r, span_y - 1) + 1):
                    ring = max(abs(x - cx), abs(y - cy))
                    column = x * span_y + y
                    lo, hi = starts[column], starts[column + 1]
                    while lo < hi:  # the column's first point at z >= cz - r (a wall along z fills it)
                        mid = (lo + hi) // 2
                        if cells[mid, 2] < cz - r:
                            lo = mid + 1
                        else:
                            hi = mid
                    for j in range(lo, starts[column + 1]):
                        z = cells[j, 2]
                        if z > cz + r:
                            break
                        if max(ring, abs(z - cz)) <= scanned:
                            continue
                        dx, dy, dz = points[j, 0] - px, points[j, 1] - py, points[j, 2] - pz
                        d = dx * dx + dy * dy + dz * dz
                        if count < k:
                            m = count
                            count += 1
                        elif d < best_d[k - 1]:
                            m = k - 1
                        else:
                            continue
                        while m > 0 and best_d[m - 1] > d:  # insertion into the sorted k best
                            best_d[m] = best_d[m - 1]
                            best_i[m] = best_i[m - 1]
                            m -= 1
                        best_d[m] = d
                        best_i[m] = j
            scanned = r
            done = count == k and best_d[k - 1] <= (r * step + face) ** 2
            if done or r >= max_radius:
                break
            r += 1
        if done:
            for m in range(k):
                found[i - base, m] = order[best_i[m]]
        else:
            found[i - base, 0] = -1
