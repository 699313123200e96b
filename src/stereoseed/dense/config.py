"""The dense stage's settings (:mod:`stereoseed.dense`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from stereoseed.validation import in_range, positive, whole

__all__ = ['DenseConfig']


@dataclass(frozen=True)
class DenseConfig:
    max_reprojection_px: float = 1.5  # paper.md: "drop points whose reprojection error exceeds ~1.5 px"
    min_angle_deg: float = 2.0  # drop points with a tiny triangulation angle
    fusion_voxel: float = 0.0  # metres; 0 = automatic (about one pixel footprint)
    # Multi-view fusion (stereoseed.dense.fusion, docs/dense.md): a point is kept when at least
    # min_support views agree on it, its own pair's two included (2 = no check). 3: one other
    # pair confirms it; a wrong propagated match lands at a random depth along its epipolar
    # line, where no other pair puts a point (fountain-P11: docs/dense.md).
    min_support: int = 3
    # The propagation's matching noise (pixels, one standard deviation of a match's position
    # along the epipolar line): what the depth tolerance of the views' agreement is derived from
    # (a point's depth noise = distance x noise / (focal x sin(angle))). Integer-pixel ZNCC
    # matches refined by a local affine fit or a parabola: a few tenths of a pixel; docs/dense.md
    # has the spread of the agreeing depths measured on fountain-P11 against this.
    match_noise_px: float = 0.3
    # Two points agree within this many standard deviations of their combined noise (3: about
    # 0.3 % of true agreements refused if the noise is Gaussian).
    agreement_sigmas: float = 3.0
    # A point is looked up in another pair's depth map within this many pixels of its image
    # (the other pair's matches are on whole pixels of its own first view, with gaps).
    lookup_px: int = 1
    # Each pair's points are checked against at most this many other pairs: those whose first
    # views share the most sparse points with its own (as COLMAP's fusion checks the images that
    # overlap the reference one). Every pair that sees a surface checks it on a walk of up to
    # this many pairs; beyond, a point's check cost would grow with the walk (a 300-photo ring:
    # 246 s of fusion, each point against all 299 pairs). 24: a ring at 15 degrees a photo, where
    # a surface is seen from a half turn (12 pairs) on either side; 0: every pair.
    check_pairs: int = 24
    # Matches found before the stop (a live run's, behind the walk: `densify`'s ``propagated``)
    # with cameras the finishing step moved since (the loop closure, a camera registered again
    # between its neighbours) no longer lie on the final epipolar geometry: a pair of which fewer
    # than this fraction reproject within max_reprojection_px is propagated again. A pair
    # propagated with its final cameras keeps 0.8-1.0 of them (templeSparseRing); one whose
    # camera moved keeps almost none.
    found_min_fraction: float = 0.5
    # A point no other pair could judge (none matched near its image in their first views: the
    # surface only a walk's end pair sees) is kept, with support 2 and confidence 0.5: nothing
    # contradicts it. On fountain-P11 they are 3 % of the points and leave the share beyond 1 %
    # of the distance at 0.4 %; dropping them took the 5-image box's ground completeness at
    # 0.5 cm from 0.70 to 0.45 (docs/dense.md). False: only confirmed points.
    keep_unjudged: bool = True
    # Points the other pairs contradict more than they confirm are dropped: confidence =
    # (agree + 1) / (agree + violate + 2) below this. 0.6: confirmed at least 1.5 times as often as
    # contradicted (measured on the fountain while the lookup still took the depth nearest X's:
    # 1.07 % of the judged points beyond 1 % of the distance at 0.5, 0.70 % at 0.6).
    min_confidence: float = 0.6
    # The propagation's images: their longer side brought down to this many pixels (0: as
    # given). Memory and time grow with the pixels (a 3072 x 2048 pair's match maps and
    # windows are 16 times a 768 x 512 one's); the points' accuracy with the resolution
    # (docs/dense.md has the fountain at both).
    resolution: int = 0
    # The pairs' first images propagated, in all, at most this many megapixels (0: no limit);
    # beyond, the resolution above is brought down for every image alike (the report and the log
    # say so). The fusion holds each pair's points and depth map: the fountain's 10 pairs at
    # 3072 x 2048 (63 MP) peak at 2.6 GiB with the whole run (docs/dense.md); 40 photos of 24
    # megapixels (940 MP) would not fit in 24 GB.
    max_megapixels: float = 64.0
    # At most this many points in dense.ply (0: no limit): the fusion voxel grown until the
    # cloud fits (a 24-megapixel walk's full-resolution cloud is tens of millions of points).
    max_points: int = 0
    # local processes for the pair jobs; 0: one per core this process may use, at most 8 (each
    # holds a pair's images and match maps, ~100 MB at 640 x 480)
    workers: int = 0

    def __post_init__(self) -> None:
        positive(self, "max_reprojection_px", "match_noise_px", "agreement_sigmas")
        if not 0 <= self.max_megapixels < math.inf:
            raise ValueError(f"DenseConfig.max_megapixels must be a finite number >= 0 (0: no limit), "
                             f"got {self.max_megapixels}")
        in_range(self, "found_min_fraction", 0.0, 1.0)
        whole(self, "workers", "lookup_px", "resolution", "max_points", "check_pairs", minimum=0)
        whole(self, "min_support", minimum=2)
        if not 0 <= self.min_confidence < 1:
            raise ValueError(f"DenseConfig.min_confidence must be in [0, 1) (0: off), got {self.min_confidence}")
        if not 0 <= self.fusion_voxel < math.inf:  # NaN too: it fused every point into one voxel
            raise ValueError(f"DenseConfig.fusion_voxel must be a finite number >= 0 (0: automatic), "
                             f"got {self.fusion_voxel}")

    def pool_size(self) -> int:
        """How many local processes run the pair jobs: ``workers``, or one per core (at most 8)."""
        from stereoseed.threads import CORES  # here: the configuration module imports nothing heavy

        return self.workers or min(CORES, 8)


@dataclass(frozen=True)
class MeshConfig:
    # Octree depth of the Poisson solve: the grid cell is scale x the cloud's largest extent
    # / 2**depth. 8: PoissonRecon's default, set on the box. 0: chosen from the cloud's point
    # spacing (cell_spacings): on a curved object depth 8 smoothed the mesh to 1.9 times its
    # cloud's error, the spacing's depth keeps it (0.85 times); it is not the default because on
    # the box its finer grid, trimmed at max_gap_cells of its smaller cells, bridges fewer of the
    # cloud's holes (completeness at 0.5 cm 0.948 against 0.956; docs/dense.md).
    depth: int = 8
    # Automatic depth: the grid cell at most this many times the cloud's point spacing (the
    # median distance of a point to its nearest neighbour): a cell spans a few points, so each
    # leaf holds the samples_per_node Poisson wants. Measured on the rendered sphere
    # (docs/dense.md): a cell of 2.7 spacings kept the cloud's accuracy, 5.5 spacings doubled its
    # error; 4 takes the box to depth 9 (3.2 spacings), where 3 took it to 10 (4x the time, 1.1 M
    # faces) for the same median.
    cell_spacings: float = 4.0
    # Automatic depth within these bounds: below 6 no object has a shape; each level more is
    # about four times the time and memory (depth 10: ~1 M faces and a minute on one core).
    min_auto_depth: int = 6
    max_auto_depth: int = 10
    # Poisson's bounding cube over the cloud's box (PoissonRecon's default): room for the
    # implicit function to close beyond the outermost points.
    scale: float = 1.1
    # Points of lower confidence (dense.ply's: (agree + 1) / (agree + contradict + 2)) are left
    # out of the mesh. 0.5: the points no other pair judged (nothing contradicts them) stay;
    # the fusion already dropped those contradicted more than confirmed (DenseConfig.min_confidence).
    min_confidence: float = 0.5
    # Minimum points per octree leaf (PoissonRecon's default): fewer make noise into surface.
    samples_per_node: float = 1.5
    # The screening weight: how strongly the surface is pulled through the points, against
    # smoothness (PoissonRecon's default for screened Poisson).
    point_weight: float = 4.0
    # A vertex farther than this many grid cells from every cloud point is not backed by the
    # cloud: Poisson bridges a hole of about its own resolution, beyond that it invents (a dome's
    # rim extrapolated at 3 or 4 cells bends its normals). On a finer grid it bridges smaller
    # holes: the box's mesh at the depth from the spacing covers 0.948 of its faces at 0.5 cm
    # against 0.956 at depth 8 (4 cells: 0.972, docs/dense.md).
    max_gap_cells: float = 2.0
    # A vertex whose Poisson density is this far below the median of the vertices the cloud
    # backs is dropped: 2 units = 16 times fewer points per area than the typical surface,
    # the density of the extrapolated rims, not of a sparsely matched but real surface.
    density_drop: float = 2.0
    # Each vertex's colour: the mean of this many nearest cloud points (a vertex stands for
    # a patch of about a grid cell, which holds several cloud points).
    color_neighbours: int = 8
    # Normals estimated (a dense.ply without them): neighbours of the local plane fit, as the
    # dense stage's own estimate uses.
    normal_neighbours: int = 10
    # Fewer cloud points cannot describe a surface at the grid's resolution: refused.
    min_points: int = 100
    # Threads of the Poisson solve (0: the cores this process may use). One: PyMeshLab's OpenMP
    # threads spin while they wait, which on cores shared with other work (the dense workers,
    # other processes) burns more than the threads gain; the wait policy cannot be changed once
    # Numba's parallel kernels have started OpenMP in the process.
    threads: int = 1

    def __post_init__(self) -> None:
        whole(self, "depth", minimum=0)
        whole(self, "min_auto_depth", "max_auto_depth", minimum=4)
        if 0 < self.depth < 4:
            raise ValueError(f"MeshConfig.depth must be 0 (from the point spacing) or >= 4, got {self.depth}")
        if not self.min_auto_depth <= self.max_auto_depth <= 12:
            raise ValueError(f"MeshConfig: min_auto_depth <= max_auto_depth <= 12 needed, got {self.min_auto_depth} "
                             f"and {self.max_auto_depth}")
        whole(self, "color_neighbours", "normal_neighbours")
        whole(self, "min_points", minimum=10)
        whole(self, "threads", minimum=0)
        positive(self, "scale", "samples_per_node", "max_gap_cells", "density_drop", "cell_spacings")

        if self.depth > 12:
            raise ValueError(f"MeshConfig.depth must be <= 12 (a finer grid needs memory no machine here has), "
                             f"got {self.depth}")
        if self.scale < 1.0:
            raise ValueError(f"MeshConfig.scale must be >= 1 (the cube holds the cloud), got {self.scale}")
        if not 0 <= self.min_confidence < 1:
            raise ValueError(f"MeshConfig.min_confidence must be in [0, 1) (0: every point), got {self.min_confidence}")
        if self.point_weight < 0:
            raise ValueError(f"MeshConfig.point_weight must be >= 0 (0: unscreened Poisson), got {self.point_weight}")

    def pool_size(self) -> int:
        from stereoseed.threads import CORES

        return self.threads or CORES
