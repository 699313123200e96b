"""The interest-point stage's settings (:mod:`stereoseed.features`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.validation import positive

__all__ = ['FeatureConfig']


@dataclass(frozen=True)
class FeatureConfig:
    harris_k: float = 0.04  # paper.md defaults table; Harris & Stephens 1988
    block_size: int = 3  # Harris structure-tensor window (OpenCV cornerHarris blockSize)
    aperture: int = 3  # Sobel aperture for the Harris gradients
    max_corners: int = 1500  # paper.md: "~1,500 strongest corners"
    min_distance: float = 6.0  # paper.md: "min spacing ~6 px"
    quality_level: float = 1e-5  # response floor relative to the strongest corner: low, so that
    # weakly textured images still get their ~1,500 strongest corners (max_corners decides)
    subpixel_window: int = 5  # half-size of the cornerSubPix search window
    # cv2.cornerSubPix's position is kept only where its junction model holds (normalised
    # residual: 0 at a perfect junction, ~0.5 on isotropic texture; 0.1 allows gradients ~18
    # degrees rms off orthogonal); elsewhere the Harris peak is refined by a quadratic fit.
    # docs/features.md has the measurements behind 0.1.
    junction_tol: float = 0.1
    # a junction moves to the intersection of its two edges, located away from the blurred apex
    # (cornerSubPix sits 0.2-0.35 px inside a blurred L corner; docs/features.md)
    edge_corners: bool = True
    border: int = 8  # corners closer than this to the image edge cannot carry a patch

    def __post_init__(self) -> None:
        positive(self, "max_corners", "min_distance", "quality_level")
        if (self.block_size < 2 or self.aperture not in (1, 3, 5, 7) or self.border < 0 or self.subpixel_window < 0
                or self.junction_tol < 0):
            raise ValueError(f"FeatureConfig: block_size >= 2, aperture 1/3/5/7, border, subpixel_window (0: off) "
                             f"and junction_tol >= 0 required, got {self.block_size}, {self.aperture}, {self.border}, "
                             f"{self.subpixel_window}, {self.junction_tol}")
