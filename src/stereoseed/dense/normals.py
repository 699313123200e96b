"""The dense cloud's normals (:func:`estimate_normals`): each point's neighbours
(:func:`stereoseed.dense.grid.neighbour_chunks`), then the compiled per-point plane fit
(:func:`pca_normals`)."""
from __future__ import annotations

import numpy as np
from numba import njit

from stereoseed.dense.grid import neighbour_chunks
from stereoseed.threads import map_chunks, split_rows

__all__ = ["estimate_normals", "pca_normals"]


def estimate_normals(points: np.ndarray, viewpoints: np.ndarray, neighbours: int = 10,
                     cell: float | None = None) -> np.ndarray:
    """Unit normals (N, 3) of a point cloud (N, 3): the direction of least spread of each point's
    ``neighbours`` nearest points (PCA), turned towards its ``viewpoints`` (N, 3) (where the
    cameras that saw it stand), so that a surface reconstruction (Poisson) knows the outside.

    cell: a grid step for the neighbour search, e.g. 1.5 fusion voxels for a fused cloud (about
    one point per voxel): the same neighbours as a k-d tree's (:func:`nearest_neighbours`),
    found about twice as fast on the dense stage's clouds. None: a k-d tree."""
    n = len(points)
    normals = np.zeros((n, 3))
    if n < 3:
        normals[:, 2] = 1.0
        return normals
    points = np.ascontiguousarray(points, np.float64)
    viewpoints = np.ascontiguousarray(viewpoints, np.float64)
    for rows, idx in neighbour_chunks(points, min(neighbours, n), cell):
        map_chunks(lambda a, b: pca_normals(points, idx, rows, viewpoints, normals, a, b), split_rows(len(rows), 50_000))
    return normals


@njit(cache=True, nogil=True, error_model="numpy")
def pca_normals(points, idx, rows, viewpoints, normals, first, end):
    """normals[i] for the points i = rows[r], r in [first, end): the eigenvector of the smallest
    eigenvalue of the scatter matrix of points[idx[r]] (its neighbours), turned towards
    viewpoints[i]. Closed form for a symmetric 3 x 3 (the trigonometric eigenvalues, then the
    largest cross product of two rows of A - lambda I), not a batched LAPACK call per point."""
    k = idx.shape[1]
    for r in range(first, end):
        i = rows[r]
        mx = my = mz = 0.0
        for j in range(k):
            p = idx[r, j]
            mx += points[p, 0]
            my += points[p, 1]
            mz += points[p, 2]
        mx /= k
        my /= k
        mz /= k
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        for j in range(k):
            p = idx[r, j]
            dx, dy, dz = points[p, 0] - mx, points[p, 1] - my, points[p, 2] - mz
            a00 += dx * dx
            a01 += dx * dy
            a02 += dx * dz
            a11 += dy * dy
            a12 += dy * dz
            a22 += dz * dz
        scale = max(abs(a00), abs(a01), abs(a02), abs(a11), abs(a12), abs(a22))
        nx, ny, nz = 0.0, 0.0, 1.0
        if scale > 0.0:
            a00, a01, a02, a11, a12, a22 = a00 / scale, a01 / scale, a02 / scale, a11 / scale, a12 / scale, a22 / scale
            q = (a00 + a11 + a22) / 3.0
            off = a01 * a01 + a02 * a02 + a12 * a12
            pp = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * off) / 6.0)
            lam = q
            if pp > 0.0:
                b00, b11, b22 = (a00 - q) / pp, (a11 - q) / pp, (a22 - q) / pp
                b01, b02, b12 = a01 / pp, a02 / pp, a12 / pp
                r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
                phi = np.arccos(min(1.0, max(-1.0, r))) / 3.0
                lam = q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest eigenvalue
            r0 = (a00 - lam, a01, a02)
            r1 = (a01, a11 - lam, a12)
            r2 = (a02, a12, a22 - lam)
            best = 0.0
            for u, v in ((r0, r1), (r0, r2), (r1, r2)):
                cx = u[1] * v[2] - u[2] * v[1]
                cy = u[2] * v[0] - u[0] * v[2]
                cz = u[0] * v[1] - u[1] * v[0]
                norm = cx * cx + cy * cy + cz * cz
                if norm > best:
                    best, nx, ny, nz = norm, cx, cy, cz
            if best > 1e-24:  # (the matrix is scaled to entries <= 1) else rounding of a zero
                norm = np.sqrt(best)
                nx, ny, nz = nx / norm, ny / norm, nz / norm
            else:  # a double smallest eigenvalue (the points on a line): any normal of the line
                nx, ny, nz = 0.0, 0.0, 1.0
                for u in (r0, r1, r2):
                    if u[0] * u[0] + u[1] * u[1] + u[2] * u[2] > 0.0:
                        cx, cy, cz = (u[1], -u[0], 0.0) if abs(u[2]) < max(abs(u[0]), abs(u[1])) else (0.0, u[2], -u[1])
                        norm = np.sqrt(cx * cx + cy * cy + cz * cz)
                        nx, ny, nz = cx / norm, cy / norm, cz / norm
                        break
        if (nx * (viewpoints[i, 0] - points[i, 0]) + ny * (viewpoints[i, 1] - points[i, 1])
                + nz * (viewpoints[i, 2] - points[i, 2])) < 0.0:
            nx, ny, nz = -nx, -ny, -nz
        normals[i, 0], normals[i, 1], normals[i, 2] = nx, ny, nz
