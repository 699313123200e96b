"""Multi-view fusion of the pairs' dense clouds (as COLMAP's fusion and the Lhuillier-Quan
paper's own multi-view step do): every point a pair triangulated is checked against every other
pair's cloud, seen from that pair's first view as a depth map (each propagated match has an
integer pixel in the pair's first image, so a pair's cloud is a sparse depth map of that view).

For point X of pair p and another pair q with first view c: X is projected into c; the pixels
within ``lookup_px`` of its image that hold one of q's points are looked at, and the one
nearest X's image is compared:

- **agree** when the depths differ by less than the tolerance their noise allows (each point's
  depth noise from the matching's: ``match_noise_px`` over its pair's angle, :func:`depth_sigma`)
  and q's point reprojects into p's first view within the matching's noise of X's pixel;
- **violate** when X lies in front of q's point by more than the tolerance: view c sees q's point
  through the place of X, so one of the two is wrong (a floater lies in front of the surface the
  other pairs see);
- nothing otherwise (X behind: hidden from c; no point there: not matched in q).

Per point: the views that agree (p's two and each agreeing pair's two, counted once) are its
support; its position is the mean of X and the agreeing points (the pairs' noise averages out);
its triangulation angle the widest between the rays of those views; its confidence
(agree + 1) / (agree + violate + 2), Laplace's estimate of the chance that another pair that
judges it agrees: 0.5 with no evidence either way, towards 1 when confirmed, towards 0 when
contradicted.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from numba import njit

from stereoseed.geometry.projection import camera_center, normalize_projection
from stereoseed.threads import map_chunks, split_rows

__all__ = ["PairCloud", "PairClouds", "PairSpool", "ViewChecks", "check_views", "check_views_by_pair", "depth_sigma",
           "every_other_pair", "overlapping_pairs"]


@dataclass(frozen=True)
class PairCloud:
    """One pair's triangulated points: points (N, 3); pixels (N, 2) int, each point's integer
    pixel in the pair's first view (the propagation's x1); angles (N,) degrees; views (a, b),
    their indices among the cameras."""

    points: np.ndarray
    pixels: np.ndarray
    angles: np.ndarray
    views: tuple[int, int]


@dataclass(frozen=True)
class PairClouds:
    """Every pair's points in one set of arrays, pair after pair: points (N, 3) float64, pixels
    (N, 2) int32 (each point's pixel in its pair's first view), angles (N,) float64 degrees,
    offsets (P + 1,) int64 (pair q's rows are offsets[q]:offsets[q + 1]) and views (P, 2) int64.
    One copy of the points, not one per pair and one stacked: at full resolution they are the
    dense stage's memory (tens of millions)."""

    points: np.ndarray
    pixels: np.ndarray
    angles: np.ndarray
    offsets: np.ndarray
    views: np.ndarray

    @classmethod
    def stack(cls, clouds: list[PairCloud]) -> "PairClouds":
        counts = np.array([len(c.points) for c in clouds], np.int64)
        n = int(counts.sum())

        def joined(arrays: list[np.ndarray], dtype: type, width: int | None) -> np.ndarray:
            shape = (n,) if width is None else (n, width)
            return np.concatenate(arrays).astype(dtype, copy=False) if n else np.zeros(shape, dtype)

        return cls(joined([c.points for c in clouds], np.float64, 3), joined([c.pixels for c in clouds], np.int32, 2),
                   joined([c.angles for c in clouds], np.float64, None), np.r_[0, np.cumsum(counts)].astype(np.int64),
                   np.array([c.views for c in clouds], np.int64).reshape(-1, 2))

    def __len__(self) -> int:
        return len(self.points)


class PairSpool:
    """The pairs' clouds as they come in, kept on disk in ``folder`` (the caller's, e.g. a
    temporary one) until :meth:`stacked`: at full resolution a pair's cloud is ~100 MB, and held
    in memory the clouds of the pairs done would add up while the pair workers hold theirs."""

    _FIELDS = (("points", np.float64, 3), ("pixels", np.int32, 2), ("angles", np.float64, None),
               ("colors", np.uint8, 3))

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.counts: list[int] = []
        self.views: list[tuple[int, int]] = []

    def add(self, cloud: PairCloud, colors: np.ndarray) -> None:
        """Keep pair ``cloud`` and its points' colours (N, 3) uint8 (after those added before)."""
        values = {"points": cloud.points, "pixels": cloud.pixels, "angles": cloud.angles, "colors": colors}
        for name, dtype, _ in self._FIELDS:
            np.save(self.folder / f"{len(self.counts)}-{name}.npy", np.asarray(values[name]).astype(dtype, copy=False),
                    allow_pickle=False)
        self.counts.append(len(cloud.points))
        self.views.append(cloud.views)

    def stacked(self) -> PairClouds:
        """Every pair's points as :meth:`PairClouds.stack` gives them, read pair after pair into
        the stacked arrays (one copy in memory); their colours stay here (:meth:`colors`)."""
        offsets = np.r_[0, np.cumsum(np.array(self.counts, np.int64))].astype(np.int64)
        n = int(offsets[-1])
        fields = self._FIELDS[:3]
        out = {name: np.empty((n,) if width is None else (n, width), dtype) for name, dtype, width in fields}
        for q, (first, end) in enumerate(zip(offsets[:-1], offsets[1:])):
            for name, _, _ in fields:
                out[name][first:end] = np.load(self.folder / f"{q}-{name}.npy", mmap_mode="r", allow_pickle=False)
        return PairClouds(out["points"], out["pixels"], out["angles"], offsets, np.array(self.views, np.int64).reshape(-1, 2))

    def colors(self, q: int) -> np.ndarray:
        """Pair q's points' colours (N_q, 3) uint8."""
        return np.load(self.folder / f"{q}-colors.npy", allow_pickle=False)


@dataclass(frozen=True)
class ViewChecks:
    """What the other pairs said of every point (the pairs' points in pair order): merged
    positions (N, 3) float64, support (N,) views, angle (N,) degrees, agree / violate
    (N,) pairs, judged (N,) the other pairs that had a point near its image (whatever their
    verdict), confidence (N,); the counts int32."""

    points: np.ndarray
    support: np.ndarray
    angle: np.ndarray
    agree: np.ndarray
    violate: np.ndarray
    judged: np.ndarray
    confidence: np.ndarray


def _focal(P: np.ndarray) -> float:
    """The focal length in pixels of a normalised camera (the mean of its two axes')."""
    return 0.5 * float(np.linalg.norm(np.cross(P[0, :3], P[2, :3])) + np.linalg.norm(np.cross(P[1, :3], P[2, :3])))


def depth_sigma(points: np.ndarray, centre: np.ndarray, focal: float, angles_deg: np.ndarray,
                noise_px: float) -> np.ndarray:
    """The standard deviation (N,) of each point's position along its ray from a two-view
    triangulation: distance x noise_px / (focal x sin(angle)); a match noise of noise_px
    pixels moves a point of triangulation angle theta by that much along the ray."""
    distance = np.linalg.norm(points - centre, axis=1)
    return distance * noise_px / (focal * np.sin(np.radians(np.maximum(angles_deg, 1e-3))))


def every_other_pair(n_pairs: int) -> np.ndarray:
    """(P, P - 1) int64: for each pair, every other one, ascending."""
    every = np.tile(np.arange(n_pairs, dtype=np.int64), (n_pairs, 1))
    return every[~np.eye(n_pairs, dtype=bool)].reshape(n_pairs, max(n_pairs - 1, 0))


def overlapping_pairs(shared: np.ndarray, limit: int) -> np.ndarray:
    """(P, K) int64: for each pair, the other pairs to check its points against, ascending, -1
    after the last: the ``limit`` whose first views share the most sparse points with its own
    (``shared`` (P, P): those counts; ties to the earlier pair), none that shares none; every other
    pair when there are at most ``limit`` (or ``limit`` is 0)."""
    n = len(shared)
    if not limit or n - 1 <= limit:
        return every_other_pair(n)
    out = np.full((n, limit), -1, np.int64)
    for p in range(n):
        counts = np.asarray(shared[p], np.int64).copy()
        counts[p] = -1
        best = np.argsort(-counts, kind="stable")[:limit]
        best = np.sort(best[counts[best] > 0])
        out[p, :len(best)] = best
    return out


def check_views(clouds: list[PairCloud] | PairClouds, cameras: list[np.ndarray], sizes: list[tuple[int, int]],
                noise_px: float, sigmas: float, lookup_px: int, others: np.ndarray | None = None) -> ViewChecks:
    """Each pair's points checked against every other pair's (module doc), or against
    ``others`` (P, K) int64 (pair p's: the pairs to check against, ascending, -1 after the last).
    cameras: (3, 4) per view index; sizes: (width, height) per view index."""
    parts: list[ViewChecks] = []
    check_views_by_pair(clouds, cameras, sizes, noise_px, sigmas, lookup_px, lambda q, checks: parts.append(checks),
                        others)
    if not parts:
        counts = np.zeros(0, np.int32)
        return ViewChecks(np.zeros((0, 3)), counts, np.zeros(0), counts, counts, counts, np.zeros(0))
    return ViewChecks(*(np.concatenate([getattr(c, f.name) for c in parts]) for f in dataclasses.fields(ViewChecks)))


def check_views_by_pair(clouds: list[PairCloud] | PairClouds, cameras: list[np.ndarray], sizes: list[tuple[int, int]],
                        noise_px: float, sigmas: float, lookup_px: int,
                        take: Callable[[int, ViewChecks], None], others: np.ndarray | None = None) -> None:
    """:func:`check_views`, pair after pair: ``take(q, checks)`` gets pair q's points' checks (its
    rows of the stack, in order) as soon as they are known, so a caller that keeps only some
    points never holds the checks of all of them (at full resolution, tens of millions)."""
    stacked = clouds if isinstance(clouds, PairClouds) else PairClouds.stack(clouds)
    Pn = np.stack([normalize_projection(np.asarray(P, np.float64)) for P in cameras])
    centres = np.stack([camera_center(P) for P in Pn])
    focal = np.array([_focal(P) for P in Pn])
    offsets, pair_views = stacked.offsets, stacked.views
    if others is None:
        others = every_other_pair(len(pair_views))
    points, pixels = np.ascontiguousarray(stacked.points), np.ascontiguousarray(stacked.pixels)
    angles = np.ascontiguousarray(stacked.angles, np.float64)  # each point's depth sigma from it, in the kernel
    # each pair's depth map: the row of its point at each pixel of its first view, -1 where none
    width = max((s[0] for s in sizes), default=1)
    height = max((s[1] for s in sizes), default=1)
    index = np.full((len(pair_views), height, width), -1, np.int32)
    for q in range(len(pair_views)):
        rows = slice(offsets[q], offsets[q + 1])
        index[q, pixels[rows, 1], pixels[rows, 0]] = np.arange(offsets[q], offsets[q + 1], dtype=np.int32)
    for q, (first, end) in enumerate(zip(offsets[:-1].tolist(), offsets[1:].tolist())):
        m = end - first
        merged = np.empty((m, 3))
        support, agree, violate, judged = (np.zeros(m, np.int32) for _ in range(4))
        angle = np.zeros(m)
        bounds = first + split_rows(m, 20_000)
        map_chunks(lambda a, b: _check(points, pixels, angles, q, pair_views, index, Pn, centres, focal,
                                       float(noise_px), float(sigmas), int(lookup_px), len(cameras), others, first,
                                       merged, support, angle, agree, violate, judged, a, b), bounds)
        confidence = (agree + 1.0) / (agree + violate + 2.0)
        take(q, ViewChecks(merged, support, angle, agree, violate, judged, confidence))


@njit(cache=True, nogil=True, inline="always")
def _project(P, X):
    h0 = P[0, 0] * X[0] + P[0, 1] * X[1] + P[0, 2] * X[2] + P[0, 3]
    h1 = P[1, 0] * X[0] + P[1, 1] * X[1] + P[1, 2] * X[2] + P[1, 3]
    z = P[2, 0] * X[0] + P[2, 1] * X[1] + P[2, 2] * X[2] + P[2, 3]
    return h0, h1, z


@njit(cache=True, nogil=True, inline="always")
def _depth_sigma(points, i, centre, focal, angle, noise_px):
    """:func:`depth_sigma` of point i, computed where it is needed: an array of every point's
    would be 140 MB more at full resolution."""
    dx, dy, dz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz) * noise_px / (focal * np.sin(np.radians(max(angle, 1e-3))))


@njit(cache=True, nogil=True, error_model="numpy")
def _check(points, pixels, angles, p, pair_views, index, Pn, centres, focal, noise_px, sigmas, lookup_px,
           n_views, others, base, merged, support, angle, agree, violate, judged, first, end):
    """The checks of points [first, end), all of pair p (check_views' module doc), written to the
    outputs' rows i - base."""
    height, width = index.shape[1], index.shape[2]
    seen = np.zeros(n_views, np.int64)  # the agreeing views of the current point: seen[v] == i + 1
    members = np.empty(n_views, np.int64)
    rays = np.empty((n_views, 3))
    for i in range(first, end):
        X = points[i]
        a = pair_views[p, 0]
        sigma_i = _depth_sigma(points, i, centres[a], focal[a], angles[i], noise_px)
        _, _, za = _project(Pn[a], X)  # X's depth in its own first view (for every pair that agrees)
        sx, sy, sz = X[0], X[1], X[2]
        count = 1
        n_members = 0
        for v in (pair_views[p, 0], pair_views[p, 1]):
            if seen[v] != i + 1:
                seen[v] = i + 1
                members[n_members] = v
                n_members += 1
        n_agree = 0
        n_violate = 0
        n_judged = 0
        for j in range(others.shape[1]):
            q = others[p, j]
            if q < 0:
                break
            c = pair_views[q, 0]
            h0, h1, z = _project(Pn[c], X)
            if z <= 0:
                continue
            fx, fy = h0 / z, h1 / z
            u = int(np.floor(fx + 0.5))
            w = int(np.floor(fy + 0.5))
            if u < -lookup_px or w < -lookup_px or u >= width + lookup_px or w >= height + lookup_px:
                continue
            # q's point nearest X's image in c: not the one nearest in depth, which would pick
            # q's noise to match X's and make the average no better than X
            best = -1
            best_gap = np.inf
            for yy in range(max(w - lookup_px, 0), min(w + lookup_px, height - 1) + 1):
                for xx in range(max(u - lookup_px, 0), min(u + lookup_px, width - 1) + 1):
                    if index[q, yy, xx] >= 0:
                        gap = (xx - fx) ** 2 + (yy - fy) ** 2
                        if gap < best_gap:
                            best_gap = gap
                            best = index[q, yy, xx]
            if best < 0:
                continue
            n_judged += 1
            Y = points[best]
            _, _, zy = _project(Pn[c], Y)
            # the lookup's offset of up to lookup_px pixels of c moves along a surface slanted
            # in c by about that footprint: allowed on top of the two points' noise
            footprint = z / focal[c] * (lookup_px + 0.5)
            sigma_best = _depth_sigma(points, best, centres[c], focal[c], angles[best], noise_px)
            tol = sigmas * np.sqrt(sigma_i ** 2 + sigma_best ** 2) + footprint
            if zy - z > tol:
                n_violate += 1
                continue
            if abs(zy - z) > tol:
                continue
            # q's point in p's first view: within the matching noise (and the lookup's offset
            # seen from there) of X's own pixel
            g0, g1, gz = _project(Pn[a], Y)
            if gz <= 0:
                continue
            dx = g0 / gz - pixels[i, 0]
            dy = g1 / gz - pixels[i, 1]
            slack = sigmas * noise_px * np.sqrt(2.0) + footprint * focal[a] / za
            if dx * dx + dy * dy > slack * slack:
                continue
            n_agree += 1
            count += 1
            sx += Y[0]
            sy += Y[1]
            sz += Y[2]
            for v in (pair_views[q, 0], pair_views[q, 1]):
                if seen[v] != i + 1:
                    seen[v] = i + 1
                    members[n_members] = v
                    n_members += 1
        mx, my, mz = sx / count, sy / count, sz / count
        o = i - base
        merged[o, 0], merged[o, 1], merged[o, 2] = mx, my, mz
        # the widest angle between two agreeing views' rays: the smallest cosine, one arccos
        for k in range(n_members):
            c1 = centres[members[k]]
            rx, ry, rz = c1[0] - mx, c1[1] - my, c1[2] - mz
            norm = np.sqrt(rx * rx + ry * ry + rz * rz)
            rays[k, 0], rays[k, 1], rays[k, 2] = rx / norm, ry / norm, rz / norm
        smallest = 1.0
        for k in range(n_members):
            for m in range(k + 1, n_members):
                smallest = min(smallest, rays[k, 0] * rays[m, 0] + rays[k, 1] * rays[m, 1] + rays[k, 2] * rays[m, 2])
        widest = np.degrees(np.arccos(max(-1.0, smallest)))
        support[o] = n_members
        angle[o] = widest
        agree[o] = n_agree
        violate[o] = n_violate
        judged[o] = n_judged
