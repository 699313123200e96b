"""Quasi-dense reconstruction (paper §4.4): match propagation on each consecutive registered
pair, seeded by its sparse matches and restricted by its known epipolar geometry; dense
triangulation with filters; fusion of the pairs' clouds into one model.

Pairs are independent jobs (:mod:`stereoseed.cluster`): a local process pool by default, or a
Dask cluster's workers; each job returns only its filtered cloud, so memory holds at most a few
pairs' match maps at a time, and the clouds are fused in pair order whichever job finished first.
"""
from __future__ import annotations

from dataclasses import dataclass

import logging
import os
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np
from numba import njit

from stereoseed.arrays import sorted_groups
from stereoseed.geometry.projection import camera_center, fundamental_from_projections
from stereoseed.geometry.resampling import ratio_of, to_frame
from stereoseed.cluster import JobPool, executor_for
from stereoseed.config import Config
from stereoseed.dense.config import DenseConfig
from stereoseed.dense.frames import budgeted_resolution, dense_frames, resized
from stereoseed.dense.fusion import PairCloud, PairClouds, PairSpool, check_views_by_pair, overlapping_pairs
from stereoseed.dense.grid import voxel_keys
from stereoseed.dense.normals import estimate_normals
from stereoseed.errors import StereoseedError
from stereoseed.matching.config import PropagationConfig
from stereoseed.io.ply import write_ply
from stereoseed.matching.propagation.core import propagate
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.rig import side_of, station_of
from stereoseed.threads import map_chunks, split_rows
from stereoseed.estimators.triangulation import triangulate_two_view

log = logging.getLogger(__name__)

__all__ = ["DenseCloud", "densify_pair", "propagate_pair", "triangulated_pair", "fuse", "densify", "dense_pairs",
           "PairJob", "pair_job", "pair_overlaps"]


def densify_pair(image_a: np.ndarray, image_b: np.ndarray, P_a: np.ndarray, P_b: np.ndarray,
                 seeds: np.ndarray, propagation: PropagationConfig = PropagationConfig(),
                 dense: DenseConfig = DenseConfig()) -> dict[str, Any]:
    """Propagate, triangulate and filter one pair (:func:`propagate_pair`, then :func:`triangulated_pair`).

    image_a, image_b: uint8 BGR; P_a, P_b: (3, 4); seeds: (S, 4). Returns a dict with
    "points" (N, 3), "colors" (N, 3) uint8 RGB, "pixels" (N, 2) int64 (each point's pixel in
    image_a), "angles" (N,) triangulation angles in degrees and "report" (counts before/after
    each filter, seconds).
    """
    matches, report = propagate_pair(image_a, image_b, P_a, P_b, seeds, propagation)
    return triangulated_pair(image_a, P_a, P_b, matches, report, dense)


def propagate_pair(image_a: np.ndarray, image_b: np.ndarray, P_a: np.ndarray, P_b: np.ndarray, seeds: np.ndarray,
                   propagation: PropagationConfig = PropagationConfig()) -> tuple[np.ndarray, dict[str, Any]]:
    """The pair's propagated matches (M, 4) float64 (x_a, y_a, x_b, y_b, in the images' pixels)
    under the epipolar geometry of P_a, P_b, and the report's counts and seconds so far: the
    dense stage's costly part, which a live run does behind the walk (:mod:`stereoseed.live`)."""
    t0 = time.perf_counter()
    F = fundamental_from_projections(P_a, P_b)
    result = propagate(image_a, image_b, seeds, F, propagation, subpixel_method=propagation.subpixel_method)
    return result.matches, {"seeds": int(len(seeds)), "seeds_used": int(result.n_seeds_used),
                            "matches": int(len(result.matches)), "seconds": {"propagation": time.perf_counter() - t0}}


def triangulated_pair(image_a: np.ndarray, P_a: np.ndarray, P_b: np.ndarray, m: np.ndarray, report: dict[str, Any],
                      dense: DenseConfig = DenseConfig()) -> dict[str, Any]:
    """The points of the pair's matches m (M, 4) (:func:`propagate_pair`'s, with its ``report``)
    triangulated with P_a, P_b and filtered: :func:`densify_pair`'s dict."""
    t1 = time.perf_counter()
    report = {**report, "seconds": {**report["seconds"], "triangulation": 0.0}}
    if len(m) == 0:
        return {"points": np.zeros((0, 3)), "colors": np.zeros((0, 3), np.uint8), "pixels": np.zeros((0, 2), np.int64),
                "angles": np.zeros(0), "report": report}
    # Three Gauss-Newton steps suffice: the linear solution of a sub-pixel match is already close.
    tri = triangulate_two_view(P_a, P_b, m[:, :2], m[:, 2:], iterations=3)
    finite = np.all(np.isfinite(tri.points), axis=1)
    in_front = finite & np.all(tri.depths > 0, axis=0)
    small_error = in_front & (tri.max_error() <= dense.max_reprojection_px)
    wide = small_error & (tri.angles >= dense.min_angle_deg)
    report.update(in_front=int(in_front.sum()), small_reprojection=int(small_error.sum()), wide_angle=int(wide.sum()))
    x1 = m[wide, :2].astype(np.int64)
    colors = image_a[x1[:, 1], x1[:, 0]][:, ::-1] if image_a.ndim == 3 else np.repeat(image_a[x1[:, 1], x1[:, 0]][:, None], 3, 1)
    report["seconds"]["triangulation"] = time.perf_counter() - t1
    return {"points": tri.points[wide], "colors": np.ascontiguousarray(colors, dtype=np.uint8), "pixels": x1,
            "angles": tri.angles[wide], "report": report}


@njit(cache=True, nogil=True, inline="always")
def _distinct_sources(order, starts, sources, g, last_group):
    """How many distinct sources the points of group g have (groups as
    :func:`~stereoseed.arrays.sorted_groups` gives them); last_group (S,) is scratch shared by
    the groups, -1 at first: each source's last group seen."""
    distinct = 0
    for j in range(starts[g], starts[g + 1]):
        s = sources[order[j]]
        if last_group[s] != g:
            last_group[s] = g
            distinct += 1
    return distinct


# the voxel kernels' groups are shared among threads in chunks of at least this many: a group
# costs tens of nanoseconds (random reads of its points), a thread tens of microseconds
_GROUPS_PER_THREAD = 50_000


def fuse(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge near-duplicates: points falling in the same voxel (size ``voxel``, metres) are
    replaced by their mean position and mean colour. (N, 3), (N, 3) -> (K, 3), (K, 3)."""
    if len(points) == 0:
        return points, colors
    return _fuse(points, colors, np.zeros(len(points), np.int64), np.zeros((1, 3)), voxel)[:2]


def _fuse(points: np.ndarray, colors: np.ndarray, sources: np.ndarray, stand: np.ndarray,
          voxel: float, groups: tuple[np.ndarray, np.ndarray] | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fuse` of a non-empty cloud whose points come from sources (N,) int (pairs, whose
    cameras stand at stand (S, 3)): the fused points (K, 3), colours (K, 3) uint8, where the
    cameras that saw each stand on average (K, 3) and how many distinct sources each has (K,).
    groups: the points' voxels as :func:`sorted_groups` gives them, when the caller has them."""
    order, starts = groups if groups is not None else sorted_groups(voxel_keys(points, voxel))
    k = len(starts) - 1
    fused, mean_colors, viewpoints, support = np.zeros((k, 3)), np.zeros((k, 3), np.uint8), np.zeros((k, 3)), np.zeros(k, np.int64)
    args = (order, starts, np.ascontiguousarray(points, np.float64), np.ascontiguousarray(colors),
            np.ascontiguousarray(sources, np.int64), np.ascontiguousarray(stand, np.float64),
            fused, mean_colors, viewpoints, support)
    map_chunks(lambda a, b: _voxel_means(*args, a, b), split_rows(k, _GROUPS_PER_THREAD))
    return fused, mean_colors, viewpoints, support


@njit(cache=True, nogil=True)
def _voxel_means(order, starts, points, colors, sources, stand, fused, mean_colors, viewpoints, support,
                 first, end):
    """Per group g in [first, end) (groups as :func:`~stereoseed.arrays.sorted_groups` gives
    them), into rows g of the zeroed outputs (K, 3), (K, 3) uint8, (K, 3), (K,): the mean point,
    mean colour (rounded half to even), mean stand[source], and the number of distinct sources.
    Each group's sums run in increasing point order, as np.bincount's do (the same bits)."""
    last_group = np.full(stand.shape[0], -1, np.int64)
    colour = np.zeros(3)  # the group's colour sum: a (K, 3) float64 array would be 200 MB at full resolution
    for g in range(first, end):
        colour[:] = 0.0
        for j in range(starts[g], starts[g + 1]):
            i = order[j]
            for a in range(3):
                fused[g, a] += points[i, a]
                colour[a] += float(colors[i, a])
                viewpoints[g, a] += stand[sources[i], a]
        support[g] = _distinct_sources(order, starts, sources, g, last_group)
        count = float(starts[g + 1] - starts[g])
        for a in range(3):
            fused[g, a] /= count
            mean_colors[g, a] = np.uint8(np.rint(colour[a] / count))
            viewpoints[g, a] /= count


def _auto_voxel(recon: Reconstruction) -> float:
    """About one pixel's footprint at the typical depth: merging finer keeps duplicates,
    coarser loses detail."""
    pts, _ = recon.live_points()
    feet = []
    for v in recon.registered_views:
        P = recon.views[v].P
        depth = np.median(np.linalg.norm(pts - camera_center(P), axis=1)) if len(pts) else 1.0
        f = np.linalg.norm(P[0, :3]) / np.linalg.norm(P[2, :3])
        feet.append(depth / f)
    return float(np.median(feet))


# a fusion voxel below this fraction of a pixel's footprint merges nothing and leaves the support
# check no neighbour (0 or 1 points came out of 1e-9 m): a unit slip (mm given for m), refused
MIN_VOXEL_OF_FOOTPRINT = 1e-3


def _fusion_voxel(recon: Reconstruction, given: float, scale: float = 1.0) -> float:
    """The fusion voxel: ``given`` (DenseConfig.fusion_voxel), else one pixel's footprint in
    images resized by ``scale``."""
    footprint = _auto_voxel(recon) / scale
    if given and given < MIN_VOXEL_OF_FOOTPRINT * footprint:
        raise StereoseedError(f"DenseConfig.fusion_voxel = {given:g}: below a thousandth of a pixel's footprint "
                              f"here ({footprint:.3g}, the calibration's unit); give 0 (automatic) or a size "
                              f"near it")
    return given or footprint


def _run_pair(args: tuple) -> dict[str, Any]:
    return densify_pair(*args)


def dense_views(recon: Reconstruction, cfg: Config) -> list[int]:
    """The registered views the dense stage pairs in order: without ``TrustConfig.keep_flagged``
    a camera the run could not vouch for (``reliable`` False) gives no dense match."""
    return [v for v in recon.registered_views if recon.views[v].reliable or cfg.trust.keep_flagged]


def dense_pairs(recon: Reconstruction, cfg: Config) -> list[tuple[int, int]]:
    """The image pairs the dense stage propagates, in the order their clouds are fused: each
    consecutive pair of :func:`dense_views`; a rig walk's stations' own pairs first (a known
    baseline, the calibrated rig), then across consecutive stations (their left images, or
    whichever images they have)."""
    views = dense_views(recon, cfg)
    if recon.rig is None:
        return list(zip(views[:-1], views[1:]))
    kept = set(views)
    own = [(v, v + 1) for v in views if side_of(v) == 0 and v + 1 in kept]
    first_of = {}  # station -> its left image, else its right one
    for v in views:
        first_of.setdefault(station_of(v), v)
    stations = sorted(first_of)
    return own + [(first_of[a], first_of[b]) for a, b in zip(stations[:-1], stations[1:])]


class PairJob(NamedTuple):
    """The arguments of :func:`densify_pair` for one pair (:func:`pair_job`); without ``dense``
    (:attr:`propagation_args`), those of :func:`propagate_pair`."""

    image_a: np.ndarray
    image_b: np.ndarray
    P_a: np.ndarray
    P_b: np.ndarray
    seeds: np.ndarray
    propagation: PropagationConfig
    dense: DenseConfig

    @property
    def propagation_args(self) -> tuple:
        return tuple(self)[:6]


def pair_job(recon: Reconstruction, pair: tuple[int, int], cfg: Config,
             frames: tuple[list[float], list[np.ndarray], list[tuple[int, int]]]) -> PairJob:
    """The job of views ``pair`` = (a, b) in the dense stage's frames
    (:func:`~stereoseed.dense.frames.dense_frames` of the views): both images at that size, their
    cameras, the sparse points they share as seeds."""
    _, cameras, sizes = frames
    a, b = pair
    seeds = np.asarray(recon.shared_pixels(a, b), np.float64).reshape(-1, 4)
    seeds = np.hstack([to_frame(seeds[:, :2], ratio_of(recon.views[a].image_size or sizes[a], sizes[a])),
                       to_frame(seeds[:, 2:], ratio_of(recon.views[b].image_size or sizes[b], sizes[b]))])
    return PairJob(resized(recon.views[a].image, sizes[a]), resized(recon.views[b].image, sizes[b]), cameras[a],
                   cameras[b], seeds, cfg.propagation, cfg.dense)


@dataclass(frozen=True)
class DenseCloud:
    """The fused quasi-dense cloud: points (N, 3) float64 in the model's frame, colors (N, 3)
    uint8 (as ``dense.ply`` stores them), normals (N, 3) unit vectors turned towards the cameras
    that saw each point; support (N,) int64, how many views agree on it (the most of its voxel's
    points, :mod:`stereoseed.dense.fusion`); angle (N,) its widest triangulation angle among them
    (degrees); confidence (N,) in (0, 1), the chance that another view judging it agrees."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray
    support: np.ndarray
    angle: np.ndarray | None = None
    confidence: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)


def densify(recon: Reconstruction, cfg: Config = Config(), out_dir: str | os.PathLike | None = None,
            pool: JobPool | None = None, progress: Callable[[int, int, str], None] | None = None,
            propagated: Mapping[tuple[int, int], tuple[str | os.PathLike, dict[str, Any]]] | None = None
            ) -> tuple[DenseCloud, dict[str, Any]]:
    """Quasi-dense stage over every consecutive registered pair (:func:`dense_pairs`); writes
    ``dense.ply`` in out_dir when given. Returns the cloud and the report (per pair counts and times, fused count).

    pool: where the pair jobs run (:func:`stereoseed.cluster.executor_for`, e.g. a Dask
    cluster); default a local pool of ``cfg.dense.pool_size()`` processes. The cloud is the same
    wherever the jobs run. progress(done, total, message): called as each pair's cloud comes in
    (total: the pairs) and once more when the fusion starts. propagated: {(a, b): (an .npy file
    of the pair's matches, its report)} found already (:func:`propagate_pair`: a live run's,
    behind the walk, with the cameras of then): those pairs are only triangulated here, with
    the cameras of now."""
    t0 = time.perf_counter()
    pairs = dense_pairs(recon, cfg)
    resolution = budgeted_resolution(recon.views, pairs, cfg.dense.resolution, cfg.dense.max_megapixels)
    frames = dense_frames(recon.views, resolution)
    lowered = None
    if resolution != cfg.dense.resolution:
        lowered = (f"{len(pairs)} image pairs at their resolution would exceed DenseConfig.max_megapixels "
                   f"({cfg.dense.max_megapixels:g}): propagated at {resolution} px on the longer side")
        log.warning("dense stage: %s", lowered)
        propagated = {}  # matches found before were found at the resolution asked for
    dc = cfg.dense
    # a pair alone cannot be confirmed by another: its points are kept, and the report says so
    alone = len(pairs) < 2
    # the pairs' clouds on disk from the first pair to the check (a run that fails or is stopped
    # takes the folder with it)
    with tempfile.TemporaryDirectory(prefix="stereoseed-dense-", ignore_cleanup_errors=True) as folder:
        spool = PairSpool(folder)
        per_pair, used = _pair_clouds(recon, cfg, pairs, frames, spool, pool, progress, propagated or {})
        if progress and pairs:
            progress(len(pairs), len(pairs), "fusing")
        t_fusion = time.perf_counter()
        others = overlapping_pairs(pair_overlaps(recon, pairs), dc.check_pairs)
        stacked = spool.stacked()  # the colours stay on disk until their pair's points are judged
        n_before = len(stacked)
        kept_points, kept_colors, kept_sources, attributes, counted = _judged(stacked, spool.colors, frames, dc, alone,
                                                                              others)
    del stacked  # only the kept points go on to the fusion
    # one pixel's footprint at the propagation's resolution
    voxel = _fusion_voxel(recon, dc.fusion_voxel, float(np.median([frames[0][v] for v in dense_views(recon, cfg)] or [1.0])))
    voxel = _voxel_for_at_most(kept_points, voxel, dc.max_points)
    fused, fused_colors, viewpoints, merged = _fused(recon, pairs, kept_points, kept_colors, kept_sources, voxel,
                                                    attributes)
    del kept_points, kept_colors, kept_sources, attributes  # before the normals' neighbour search
    # a neighbour grid 1.5 voxels wide: the ten nearest of a fused point (one a voxel) are mostly
    # within its cube of 27 cells (measured on the 18-image ring: 20 % faster than 1 voxel)
    normals = estimate_normals(fused, viewpoints, cell=1.5 * voxel) if len(fused) else np.zeros((0, 3))
    del viewpoints
    report = {"pairs": per_pair, "pairs_found_before": used,
              "points_before_fusion": n_before,
              "points_supported": counted["points_supported"], "points_unjudged": counted["points_unjudged"],
              "points": int(len(fused)),
              "support_histogram": counted["support_histogram"],
              "min_support": dc.min_support, "fusion_voxel_m": voxel, "resolution_scale": min(frames[0], default=1.0),
              "seconds": time.perf_counter() - t0, "fusion_seconds": time.perf_counter() - t_fusion,
              "peak_memory_mb": _peak_memory_mb()}
    if lowered:
        report["resolution_lowered"] = lowered
    if alone and pairs:
        report["note"] = (f"{len(pairs)} image pair: no other pair can confirm a point (--min-support "
                          f"{dc.min_support} is off), so wrong matches are not removed")
        log.warning("dense stage: %s", report["note"])
    if out_dir is not None:
        write_ply(Path(out_dir) / "dense.ply", fused, fused_colors,
                  {"nx": normals[:, 0].astype(np.float32), "ny": normals[:, 1].astype(np.float32),
                   "nz": normals[:, 2].astype(np.float32), "support": merged["support"].astype(np.int32),
                   "angle": merged["angle"].astype(np.float32),
                   "confidence": merged["confidence"].astype(np.float32)})
    return DenseCloud(fused, fused_colors, normals, merged["support"], merged["angle"], merged["confidence"]), report


def _pair_clouds(recon: Reconstruction, cfg: Config, pairs: list[tuple[int, int]], frames: tuple, spool: PairSpool,
                 pool: JobPool | None, progress: Callable[[int, int, str], None] | None,
                 propagated: Mapping[tuple[int, int], tuple[str | os.PathLike, dict[str, Any]]]
                 ) -> tuple[list[dict[str, Any]], int]:
    """Every pair's cloud into ``spool``, in pair order (:func:`densify`'s arguments): the pairs'
    reports and how many pairs' matches found before were used."""
    per_pair: list[dict[str, Any]] = []
    todo = [pair for pair in pairs if pair not in propagated]
    used = 0  # the pairs whose matches found before still lie on the final epipolar geometry
    local = executor_for(None, max(min(cfg.dense.pool_size(), len(todo)), 1)) if pool is None else nullcontext(pool)
    with local as jobs:
        computed = jobs.in_order(_run_pair, (pair_job(recon, pair, cfg, frames) for pair in todo))
        # the pool's first jobs sent before any pair is triangulated here: they run meanwhile
        first = [next(computed)] if todo and len(todo) < len(pairs) else []
        for i, pair in enumerate(pairs):
            if pair in propagated:  # its matches found already: triangulated with the cameras of now
                path, found = propagated[pair]
                a, b = pair
                res = triangulated_pair(resized(recon.views[a].image, frames[2][a]), frames[1][a], frames[1][b],
                                        np.load(path, allow_pickle=False), found, cfg.dense)
                if res["report"].get("small_reprojection", 0) < cfg.dense.found_min_fraction * found["matches"]:
                    log.info("dense stage: %s-%s's cameras moved since its matches were found; propagated again",
                             recon.views[a].name, recon.views[b].name)
                    res = densify_pair(*pair_job(recon, pair, cfg, frames))
                else:
                    used += 1
            else:
                res = (first.pop() if first else next(computed)).result()
            spool.add(PairCloud(res["points"], res["pixels"], res["angles"], pair), res["colors"])
            per_pair.append({"pair": [recon.views[pair[0]].name, recon.views[pair[1]].name], **res["report"]})
            if progress:
                progress(i + 1, len(pairs), f"{per_pair[-1]['matches']} matches")
    return per_pair, used


def pair_overlaps(recon: Reconstruction, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(P, P) int64: how many live sparse points the first views of each two ``pairs`` both
    observe (a rig walk's station pair and its pair with the next station start from the same
    view: counted once per distinct view, then given to each pair)."""
    firsts, slot = np.unique(np.array([a for a, _ in pairs], np.int64), return_inverse=True)
    shared = recon.shared_points(recon.alive[recon.obs_point] & np.isin(recon.obs_view, firsts))
    counts = np.rint(shared[firsts][:, firsts].toarray()).astype(np.int64)
    return counts[np.ix_(slot.reshape(-1), slot.reshape(-1))]


def _judged(stacked: PairClouds, colors: Callable[[int], np.ndarray], frames: tuple, dc: Any, alone: bool,
            others: np.ndarray) -> tuple:
    """The points the other pairs' checks keep (:func:`stereoseed.dense.fusion.check_views_by_pair`,
    pair after pair: the checks of all points are never held at once): their merged positions
    (K, 3), colours (K, 3), pairs (K,) int32, {"support", "angle", "confidence"} (K,) each, and
    the counts the report gives. A point no other pair could judge (none matched near its image
    in their views: the walk's ends) cannot be confirmed; kept or not as
    ``DenseConfig.keep_unjudged`` says."""
    parts: tuple[list[np.ndarray], ...] = tuple([] for _ in range(6))  # per field: each pair's kept rows
    counted = {"points_supported": 0, "points_unjudged": 0}
    histogram = np.zeros(2, np.int64)

    def take(q: int, checks: Any) -> None:
        nonlocal histogram
        keep = (checks.support >= (2 if alone else dc.min_support)) & (checks.confidence >= dc.min_confidence)
        if dc.keep_unjudged:
            keep |= checks.judged == 0
        kept = np.flatnonzero(keep)  # take() by index: 3x faster than a boolean mask on rows
        for part, values in zip(parts, (checks.points.take(kept, axis=0), colors(q).take(kept, axis=0),
                                        np.full(len(kept), q, np.int32), checks.support.take(kept),
                                        checks.angle.take(kept), checks.confidence.take(kept))):
            part.append(values)
        counted["points_supported"] += len(kept)
        counted["points_unjudged"] += int(np.sum(checks.judged == 0))
        counts = np.bincount(checks.support, minlength=2)
        histogram = np.pad(histogram, (0, max(0, len(counts) - len(histogram))))
        histogram[:len(counts)] += counts

    check_views_by_pair(stacked, frames[1], frames[2], dc.match_noise_px, dc.agreement_sigmas, dc.lookup_px, take,
                        others)
    counted["support_histogram"] = histogram.tolist()[2:] if len(stacked) else []
    if not parts[0]:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32), \
            {"support": np.zeros(0, np.int32), "angle": np.zeros(0), "confidence": np.zeros(0)}, counted

    def joined(part: list[np.ndarray]) -> np.ndarray:  # field by field, each let go once joined: one copy at most
        whole = np.concatenate(part)
        part.clear()
        return whole

    points, cols, sources, support, angle, confidence = (joined(part) for part in parts)
    return points, cols, sources, {"support": support, "angle": angle, "confidence": confidence}, counted


def _voxel_for_at_most(points: np.ndarray, voxel: float, max_points: int) -> float:
    """The fusion voxel, grown until the points (N, 3) fill at most ``max_points`` voxels (0: as
    given). A surface's voxel count goes as 1 / voxel**2: each try scales the voxel by the
    square root of the excess (and 2 % more, so a count right at the limit does not repeat)."""
    if not max_points:
        return voxel
    for _ in range(_VOXEL_TRIES):
        count = len(np.unique(voxel_keys(points, voxel))) if len(points) else 0
        if count <= max_points:
            return voxel
        voxel *= 1.02 * np.sqrt(count / max_points)
    return voxel


# how many voxel sizes --max-points tries (a surface's count falls by the factor asked each time,
# within a few per cent; a cloud of scattered points, as 1 / voxel**3, faster)
_VOXEL_TRIES = 8


def _peak_memory_mb() -> dict[str, float] | None:
    """The peak resident memory (MB) of this process and of its largest finished child (the
    local pair workers) so far; None where the platform does not say (no ``resource``)."""
    try:
        import resource
    except ImportError:
        return None
    unit = 1024 if os.uname().sysname != "Darwin" else 1024 * 1024  # ru_maxrss: KB on Linux, bytes on macOS
    return {"process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / unit,
            "largest_worker": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / unit}


def _fused(recon: Reconstruction, pairs: list[tuple[int, int]], points: np.ndarray, colors: np.ndarray,
           sources: np.ndarray, voxel: float, attributes: dict[str, np.ndarray]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`fuse`, plus where the cameras that saw each fused point stand (the pairs' middles,
    averaged over its voxel's points: its normal is turned towards them) and its attributes over
    its voxel's points: the largest support and angle, the mean confidence."""
    if len(points) == 0:
        return points, colors, np.zeros((0, 3)), {k: v[:0] for k, v in attributes.items()}
    stand = np.array([0.5 * (recon.views[a].center + recon.views[b].center) for a, b in pairs])
    order, starts = sorted_groups(voxel_keys(points, voxel))  # once: the means and the attributes' groups
    fused, fused_colors, viewpoints, _ = _fuse(points, colors, sources, stand, voxel, (order, starts))
    first = starts[:-1]
    merged = {"support": np.maximum.reduceat(attributes["support"][order], first).astype(np.int64),
              "angle": np.maximum.reduceat(attributes["angle"][order], first),
              "confidence": np.add.reduceat(attributes["confidence"][order], first) / np.diff(starts)}
    return fused, fused_colors, viewpoints, merged
