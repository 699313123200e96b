"""The dense stage's settings (:mod:`stereoseed.dense`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from stereoseed.validation import positive, whole

__all__ = ['DenseConfig']


@dataclass(frozen=True)
class DenseConfig:
    max_reprojection_px: float = 1.5  # paper.md: "drop points whose reprojection error exceeds ~1.5 px"
    min_angle_deg: float = 2.0  # drop points with a tiny triangulation angle
    fusion_voxel: float = 0.0  # metres; 0 = automatic (about one pixel footprint)
    # Multi-pair support (ours): keep a dense point when a cell of support_cell_voxels fusion
    # voxels around it holds points from >= min_pair_support pairs (1 = off). Removes the
    # propagation's wrong matches (random depths along the epipolar line); docs/benchmarks.md
    # has the share of templeSparseRing's points inside the object's box with and without it.
    min_pair_support: int = 2
    support_cell_voxels: float = 4.0
    # local processes for the pair jobs; 0: one per core this process may use, at most 8 (each
    # holds a pair's images and match maps, ~100 MB at 640 x 480)
    workers: int = 0

    def __post_init__(self) -> None:
        positive(self, "max_reprojection_px", "min_pair_support", "support_cell_voxels")
        whole(self, "workers", minimum=0)
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
    # / 2**depth. PoissonRecon's default; each level more is about three times the time and
    # memory for detail finer than the dense cloud's own noise at the scenes' sizes.
    depth: int = 8
    # Poisson's bounding cube over the cloud's box (PoissonRecon's default): room for the
    # implicit function to close beyond the outermost points.
    scale: float = 1.1
    # Minimum points per octree leaf (PoissonRecon's default): fewer make noise into surface.
    samples_per_node: float = 1.5
    # The screening weight: how strongly the surface is pulled through the points, against
    # smoothness (PoissonRecon's default for screened Poisson).
    point_weight: float = 4.0
    # A vertex farther than this many grid cells from every cloud point is not backed by the
    # cloud: Poisson bridges a hole of about its own resolution, beyond that it invents.
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
        whole(self, "depth", minimum=4)
        whole(self, "color_neighbours", "normal_neighbours")
        whole(self, "min_points", minimum=10)
        whole(self, "threads", minimum=0)
        positive(self, "scale", "samples_per_node", "max_gap_cells", "density_drop")
        if self.depth > 12:
            raise ValueError(f"MeshConfig.depth must be <= 12 (a finer grid needs memory no machine here has), "
                             f"got {self.depth}")
        if self.scale < 1.0:
            raise ValueError(f"MeshConfig.scale must be >= 1 (the cube holds the cloud), got {self.scale}")
        if self.point_weight < 0:
            raise ValueError(f"MeshConfig.point_weight must be >= 0 (0: unscreened Poisson), got {self.point_weight}")

    def pool_size(self) -> int:
        from stereoseed.threads import CORES

        return self.threads or CORES
