"""The estimators' settings: triangulation, resection, bundle adjustment.

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.validation import positive, whole, in_range

__all__ = ['TriangulationConfig', 'ResectionConfig', 'BundleConfig']


@dataclass(frozen=True)
class TriangulationConfig:
    max_reprojection_px: float = 2.0  # reject points reprojecting farther than this in any view
    min_angle_deg: float = 1.0  # tiny triangulation angles give unbounded depth error
    lm_iterations: int = 10  # per-point Gauss-Newton/LM steps (converges in 3-5)

    def __post_init__(self) -> None:
        positive(self, "max_reprojection_px")
        in_range(self, "min_angle_deg", 0.0, 90.0)
        in_range(self, "lm_iterations", 0, 1000)


@dataclass(frozen=True)
class ResectionConfig:
    min_points: int = 6  # paper eq. 10-11: 11 DOF need 6 points (2 equations each)
    ransac_threshold_px: float = 2.0  # paper.md: "6-point DLT in RANSAC, 2 px"
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    min_inliers: int = 12  # below this an insertion is reported as failed
    max_rms_px: float = 3.0  # "wild reprojection error" guard after refinement
    coplanarity_tol: float = 1e-3  # smallest/largest singular value of centred 3D points
    seed: int = 0
    # An 11-DOF camera must still look like a physical one (HZ §6.2.4 and §7.2: the principal
    # point is the worst-determined part of a DLT camera): principal point within this fraction
    # of the image diagonal of the calibrated camera's, pixel aspect and skew within these
    # relative bounds. Measured: well-conditioned resections stay within 9 px, 0.2 %, 0.0035;
    # the ill-conditioned ones (plain box, temple) leave them by far (90-1400 px, 5-90 %, 0.02-40).
    max_principal_point_shift: float = 0.1
    max_aspect_change: float = 0.03
    max_skew: float = 0.01
    # A new focal length (the "focal" model) is taken over the previous image's only when its BIC
    # is lower by more than this: strong evidence (Kass & Raftery 1995, JASA 90:773). With 30-40
    # noisy points a difference of ~0.4 picked a 14 % zoom 80 mm off on templeSparseRing.
    zoom_evidence_bic: float = 6.0

    def __post_init__(self) -> None:
        positive(self, "ransac_threshold_px", "ransac_max_iters", "max_rms_px", "coplanarity_tol",
                  "max_principal_point_shift", "max_aspect_change", "max_skew")
        if not 0.0 < self.ransac_confidence < 1.0:
            raise ValueError(f"ResectionConfig.ransac_confidence must be within (0, 1), got {self.ransac_confidence!r}")
        if self.min_points < 6 or self.min_inliers < self.min_points:
            raise ValueError(f"ResectionConfig: min_points >= 6 (the DLT) and min_inliers >= min_points required, "
                             f"got {self.min_points}, {self.min_inliers}")


@dataclass(frozen=True)
class BundleConfig:
    huber_px: float = 1.0  # paper.md: "Huber loss ~1 px"
    max_iterations: int = 20  # paper.md: "10-20 LM iterations"
    # A global BA is repeated after dropping outliers while its round dropped more than this
    # fraction of the observations (a smaller drop cannot move the solution measurably; see
    # docs/mapper.md), at most global_rounds times (COLMAP's global BA also re-runs after filtering).
    negligible_drop: float = 0.001
    global_rounds: int = 4
    # A global BA whose reduced camera system costs more than this many track-length² blocks
    # to form (sum over points of their track length squared) adjusts the cameras on a subset
    # of the points, subset_cells x subset_cells per image, then the other points alone (ours,
    # after Theia's track subset selection). The subset costs precision (the 300-image ring:
    # 0.86 cm mean centre error instead of 0.66), so only past ~4x that ring (2.3e7 blocks,
    # ~0.3 s a Levenberg-Marquardt iteration on 2 cores), where a whole BA takes minutes;
    # docs/scaling.md
    subset_above: float = 1e8
    subset_cells: int = 8

    def __post_init__(self) -> None:
        positive(self, "huber_px", "subset_above")
        whole(self, "max_iterations", "global_rounds", "subset_cells")
        in_range(self, "negligible_drop", 0.0, 1.0)
