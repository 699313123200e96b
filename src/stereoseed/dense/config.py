"""The dense stage's settings (:mod:`stereoseed.dense`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

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
        if self.fusion_voxel < 0:
            raise ValueError(f"DenseConfig.fusion_voxel must be >= 0 (0: automatic), got {self.fusion_voxel}")

    def pool_size(self) -> int:
        """How many local processes run the pair jobs: ``workers``, or one per core (at most 8)."""
        from stereoseed.threads import CORES  # here: the configuration module imports nothing heavy

        return self.workers or min(CORES, 8)
