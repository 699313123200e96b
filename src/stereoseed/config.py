"""All tunable parameters, one frozen dataclass per stage, gathered in :class:`Config`.

Every default states its source. "paper" is "Incremental Multi-view 3D Reconstruction Starting
from Two Images Taken by a Stereo Pair of Cameras" (see ../shared/paper.md); "LQ02" is
Lhuillier & Quan, "Match propagation for image-based modeling and rendering", PAMI 2002;
"HZ" is Hartley & Zisserman, Multiple View Geometry, 2nd ed.
"""
from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field
from typing import Any
from stereoseed.geometry.models import MODELS, CameraModel


def _positive(cfg: Any, *names: str) -> None:
    for name in names:
        value = getattr(cfg, name)
        if not value > 0:
            raise ValueError(f"{type(cfg).__name__}.{name} must be > 0, got {value!r}")


def _whole(cfg: Any, *names: str, minimum: int = 1) -> None:
    for name in names:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
            raise ValueError(f"{type(cfg).__name__}.{name} must be a whole number >= {minimum}, got {value!r}")


def _as_tuple(cfg: Any, name: str) -> None:
    """Sequences are stored as tuples: the frozen config stays hashable."""
    object.__setattr__(cfg, name, tuple(getattr(cfg, name)))


def _in_range(cfg: Any, name: str, low: float, high: float) -> None:
    value = getattr(cfg, name)
    if not low <= value <= high:
        raise ValueError(f"{type(cfg).__name__}.{name} must be within [{low}, {high}], got {value!r}")


def _one_of(cfg: Any, name: str, choices: tuple[str, ...], optional: bool = False) -> None:
    value = getattr(cfg, name)
    if value not in choices and not (optional and value is None):
        raise ValueError(f"{type(cfg).__name__}.{name} must be one of {', '.join(choices)}"
                         f"{' (or None)' if optional else ''}, got {value!r}")


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
        _positive(self, "max_corners", "min_distance", "quality_level")
        if (self.block_size < 2 or self.aperture not in (1, 3, 5, 7) or self.border < 0 or self.subpixel_window < 0
                or self.junction_tol < 0):
            raise ValueError(f"FeatureConfig: block_size >= 2, aperture 1/3/5/7, border, subpixel_window (0: off) "
                             f"and junction_tol >= 0 required, got {self.block_size}, {self.aperture}, {self.border}, "
                             f"{self.subpixel_window}, {self.junction_tol}")


@dataclass(frozen=True)
class MatchingConfig:
    """Every threshold of the matching stage (:mod:`stereoseed.matching`); see docs/matching.md.

    The plain ZNCC matcher (:func:`stereoseed.matching.zncc.match_zncc`) uses the paper's
    ``min_zncc`` and ``max_ratio``; the pair recipe (:func:`stereoseed.matching.pair.match_pair`)
    uses the looser ``candidate_min_zncc``, ``first_pass_ratio`` and ``guided_max_ratio`` for its
    candidates, the localisation check (``max_shift_px``, ``min_aligned_zncc``) being its
    acceptance test.
    """

    patch_size: int = 11  # paper.md: "11x11 ZNCC"
    min_zncc: float = 0.8  # paper.md: "threshold 0.8"; the acceptance threshold of plain match_zncc
    mutual: bool = True  # paper.md: "mutual best"
    search_radius: float = 0.25  # fraction of the image width; paper.md "~25 % of width"
    epipolar_band_px: float = 2.0  # max distance to the epipolar line when both cameras are known
    # Lowe's ratio on descriptor distances sqrt(2 - 2 ZNCC) against the best competitor farther
    # than patch_size / 2 from the winner (None: no uniqueness test): Lowe, IJCV 2004, chose 0.8
    max_ratio: float | None = 0.8
    # match_pair's candidates (ours): below the paper's min_zncc on purpose, the localisation check
    # being the acceptance test (true matches under foreshortening score 0.6-0.8 unaligned)
    candidate_min_zncc: float = 0.6
    first_pass_ratio: float | None = None  # match_pair without F: no uniqueness test (it starves RANSAC)
    guided_max_ratio: float | None = 0.9  # match_pair's epipolar-guided candidates: the band and the check reject the rest
    # image-2 patches also sampled at these scales by match_pair (zoom between views): any scale
    # ratio in [0.76, 1.31] is then within 9.5 % of a sampled one, which 11x11 ZNCC tolerates
    scales: tuple[float, ...] = (1 / 1.2, 1.2)
    ransac_threshold_px: float = 1.0  # paper.md: RANSAC for F, "~1 px"
    ransac_confidence: float = 0.999  # paper.md
    ransac_max_iters: int = 5000
    seed: int = 0  # RANSAC randomness, for deterministic runs
    ransac_runs: int = 3  # robust F runs per pair, the best supported kept (ours: weak pairs vary by seed)
    ransac_enough_inliers: int = 100  # a run with this many inliers ends the search (not a weak pair)
    min_f_inliers: int = 15  # F's minimal sample is 7-8 points: a consensus barely above it is no evidence
    # Localisation check (ours): the two detections of a match must align (affine) within
    # max_shift_px with aligned ZNCC > min_aligned_zncc. Strict values keep >= 95 % of matches
    # within 1 px on the synthetic box; when they keep fewer than relax_below matches (real
    # images: plaster, lighting, strong foreshortening; measured on templeSparseRing they keep
    # ~25 % of the epipolar candidates) the pair is matched again with the relaxed values
    # (:meth:`relaxed`) and robust estimation takes care of the extra outliers.
    max_shift_px: float = 0.75
    min_aligned_zncc: float = 0.9
    relax_below: int = 100
    relaxed_max_shift_px: float = 1.5
    relaxed_min_aligned_zncc: float = 0.8
    align_patch_size: int = 15  # alignment patch: six affine parameters need more pixels than a score
    align_max_iters: int = 30  # Gauss-Newton iterations of the alignment (converges in ~5-10)
    align_tol_px: float = 0.01  # the alignment stops when its translation moves less than this

    def __post_init__(self) -> None:
        def check(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(f"MatchingConfig: {message}")

        for name in ("patch_size", "align_patch_size"):
            v = getattr(self, name)
            check(isinstance(v, int) and v > 0 and v % 2 == 1, f"{name} must be an odd positive integer, got {v!r}")
        for name in ("min_zncc", "candidate_min_zncc", "min_aligned_zncc", "relaxed_min_aligned_zncc"):
            v = getattr(self, name)
            check(-1.0 <= v <= 1.0, f"{name} is a ZNCC threshold in [-1, 1], got {v!r}")
        for name in ("max_ratio", "first_pass_ratio", "guided_max_ratio"):
            v = getattr(self, name)
            check(v is None or 0.0 < v <= 1.0, f"{name} must be None (no uniqueness test) or in (0, 1], got {v!r}")
        for name in ("search_radius", "epipolar_band_px", "ransac_threshold_px", "max_shift_px",
                     "relaxed_max_shift_px", "align_tol_px"):
            v = getattr(self, name)
            check(v > 0, f"{name} must be positive, got {v!r}")
        check(0.0 < self.ransac_confidence < 1.0, f"ransac_confidence must be in (0, 1), got {self.ransac_confidence!r}")
        for name in ("ransac_max_iters", "ransac_runs", "align_max_iters"):
            v = getattr(self, name)
            check(v >= 1, f"{name} must be at least 1, got {v!r}")
        for name in ("ransac_enough_inliers", "min_f_inliers", "relax_below"):
            v = getattr(self, name)
            check(v >= 0, f"{name} must not be negative, got {v!r}")
        scales = tuple(float(s) for s in self.scales)
        check(all(s > 0 for s in scales), f"scales must be positive, got {self.scales!r}")
        object.__setattr__(self, "scales", scales)  # a tuple, so the config stays hashable

    def relaxed(self) -> "MatchingConfig":
        """This configuration with the relaxed localisation check (for a pair that kept fewer than
        ``relax_below`` matches): only ``max_shift_px`` and ``min_aligned_zncc`` change."""
        return dataclasses.replace(self, max_shift_px=self.relaxed_max_shift_px,
                                   min_aligned_zncc=self.relaxed_min_aligned_zncc)


@dataclass(frozen=True)
class TriangulationConfig:
    max_reprojection_px: float = 2.0  # reject points reprojecting farther than this in any view
    min_angle_deg: float = 1.0  # tiny triangulation angles give unbounded depth error
    lm_iterations: int = 10  # per-point Gauss-Newton/LM steps (converges in 3-5)

    def __post_init__(self) -> None:
        _positive(self, "max_reprojection_px")
        _in_range(self, "min_angle_deg", 0.0, 90.0)
        _in_range(self, "lm_iterations", 0, 1000)


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
        _positive(self, "ransac_threshold_px", "ransac_max_iters", "max_rms_px", "coplanarity_tol",
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
        _positive(self, "huber_px", "subset_above")
        _whole(self, "max_iterations", "global_rounds", "subset_cells")
        _in_range(self, "negligible_drop", 0.0, 1.0)


@dataclass(frozen=True)
class PropagationConfig:
    window: int = 5  # LQ02 / paper.md: 5x5 ZNCC
    min_zncc: float = 0.5  # LQ02: acceptance threshold
    min_texture: float = 0.01  # LQ02: s(x) > 0.01 for intensities in [0, 1]
    neighbourhood: int = 2  # LQ02: 5x5 neighbourhood (radius 2)
    disparity_gradient: int = 1  # LQ02: +-1 px disparity-gradient limit
    epipolar_band_px: float = 1.0  # paper.md: "within ~1 px of the epipolar line"
    subpixel: bool = True  # refine each whole-pixel match (ours; propagation alone rounds up to 0.7 px)
    # "affine": ZNCC of an affine-warped window maximised along the epipolar line (ours: the 5x5
    # window's shear at wide baselines moves the plain ZNCC peak by a pixel); "quadratic": 3x3 fit
    subpixel_method: str = "affine"

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"PropagationConfig.window must be odd and >= 3, got {self.window}")
        _in_range(self, "min_zncc", -1.0, 1.0)
        _positive(self, "neighbourhood", "epipolar_band_px")
        _one_of(self, "subpixel_method", ("affine", "quadratic"))


@dataclass(frozen=True)
class DenseConfig:
    max_reprojection_px: float = 1.5  # paper.md: "drop points whose reprojection error exceeds ~1.5 px"
    min_angle_deg: float = 2.0  # drop points with a tiny triangulation angle
    fusion_voxel: float = 0.0  # metres; 0 = automatic (about one pixel footprint)
    # Multi-pair support (ours): keep a dense point when a cell of support_cell_voxels fusion
    # voxels around it holds points from >= min_pair_support pairs (1 = off). Removes the
    # propagation's wrong matches (random depths along the epipolar line): measured on
    # templeSparseRing, 95 % -> see the closing note of issue 5 of the points inside the object's box.
    min_pair_support: int = 2
    support_cell_voxels: float = 4.0
    # local processes for the pair jobs; 0: one per core this process may use, at most 8 (each
    # holds a pair's images and match maps, ~100 MB at 640 x 480)
    workers: int = 0

    def __post_init__(self) -> None:
        _positive(self, "max_reprojection_px", "min_pair_support", "support_cell_voxels")
        _whole(self, "workers", minimum=0)
        if self.fusion_voxel < 0:
            raise ValueError(f"DenseConfig.fusion_voxel must be >= 0 (0: automatic), got {self.fusion_voxel}")

    def pool_size(self) -> int:
        """How many local processes run the pair jobs: ``workers``, or one per core (at most 8)."""
        from stereoseed.threads import CORES  # here: the configuration module imports nothing heavy

        return self.workers or min(CORES, 8)


@dataclass(frozen=True)
class QuasiDenseConfig:
    """Registration of weakly textured views by match propagation (Lhuillier & Quan, PAMI 2005;
    :mod:`stereoseed.sfm.registration.quasi_dense`, docs/quasi_dense.md): used only when the sparse
    chain is weak."""

    enabled: bool = True
    # the sparse chain is weak below this many resection inliers; None: the chain the motion
    # prior already distrusts, MotionPriorConfig.trusted_chain_factor x ResectionConfig.min_inliers
    weak_chain_inliers: int | None = None
    # LQ05 resample the quasi-dense matches on a grid, one match (the best ZNCC) per cell
    grid_cell_px: int = 8
    sift_ratio: float = 0.8  # Lowe 2004: the nearest SIFT descriptor clearly nearer than the second
    # robust F on the grid matches (OpenCV USAC MAGSAC): Sampson threshold, confidence, iterations
    f_threshold_px: float = 1.0
    f_confidence: float = 0.999
    f_max_iters: int = 10000
    # a chained 3D-2D pair must lie within this distance of the robust F's epipolar lines
    # (MatchingConfig.epipolar_band_px's role for the sparse matches)
    chain_epipolar_px: float = 2.0
    # propagate again from the robust F's grid inliers, within chain_epipolar_px of its lines
    second_pass: bool = False
    # after the commit, the propagated matches enter the model as tracks (grid points in both
    # views, the previous pair's points as three-view points). Off: the previous pair's points
    # are rebuilt when needed anyway, and as BA observations the propagated matches cost accuracy
    # (templeSparseRing, accurate: median / worst centre error 4.0 / 13.5 mm with them, 0.86 /
    # 2.0 mm without; dinoSparseRing median 28 mm with, 15 mm without)
    keep_tracks: bool = False
    # 8-bit grey below which a pixel is background (a black backdrop), kept out of propagation;
    # None: no background. dinoSparseRing (black backdrop), accurate mode: 16 of 16 registered,
    # median centre error 480 mm without the mask, 28 mm with it (grey 40)
    background_grey: int | None = 40
    # A quasi-dense camera is judged by the propagated matches' epipolar geometry (the median
    # distance of the robust F's grid inliers to the camera's epipolar lines), which does not
    # depend on the chained 3D points. A zoom is taken only when the zoomed camera's median is at
    # most zoom_epipolar_ratio times the unzoomed one's: the resection's BIC counts hundreds of
    # correlated propagated pairs as independent evidence. Measured ratios: real zooms of 4-7 %
    # (synthetic box, faint texture) 0.10-0.57; spurious zooms of 10-19 % on dinoSparseRing
    # (each 60-120 mm off, unzoomed 2-25 mm) 0.93-1.10
    zoom_epipolar_ratio: float = 0.5
    # the chosen camera's median must be within this factor of the robust F's own (the best any
    # epipolar geometry does on these matches), and never below f_threshold_px. dinoSparseRing:
    # cameras 0.3-14 mm off 0.84-1.43, cameras 80-280 mm off 2.4 and more
    camera_epipolar_factor: float = 2.0

    def __post_init__(self) -> None:
        if self.weak_chain_inliers is not None:
            _whole(self, "weak_chain_inliers")
        _whole(self, "grid_cell_px", "f_max_iters")
        _in_range(self, "sift_ratio", 0.0, 1.0)
        _in_range(self, "f_confidence", 0.0, 1.0)
        _positive(self, "f_threshold_px", "chain_epipolar_px")
        _in_range(self, "zoom_epipolar_ratio", 0.0, 1.0)
        if not self.camera_epipolar_factor >= 1.0:
            raise ValueError(f"QuasiDenseConfig.camera_epipolar_factor must be >= 1 (the robust F is the floor), got "
                             f"{self.camera_epipolar_factor!r}")


MODES = ("paper", "accurate")
BA_POLICIES = ("local", "global", "final")
CAMERA_MODELS = MODELS


@dataclass(frozen=True)
class MotionPriorConfig:
    """Registration without epipolar geometry (repeated patterns, weak texture): the camera is
    predicted from the previous motion, the recent points are paired with the interest points
    near their predicted pixels, and robust 2D similarities give hypotheses whose cameras
    compete by the points they explain (docs/mapper.md)."""

    # search radii around the prediction, fractions of the image width: the near search and the
    # wide one (a prediction already a few centimetres off misses by ~55 px at 640 px)
    radius_fractions: tuple[float, ...] = (0.08, 0.16)
    min_zncc: float = 0.7  # a pairing's patches must still look alike (between the paper's 0.8 and 0.6)
    # hypotheses drawn from each point's best 3 and best 6 pairings: on a repeated pattern the
    # true pairing may rank anywhere among equally good patches
    pairings_per_point: tuple[int, ...] = (3, 6)
    hypotheses_per_search: int = 3  # the pattern shifted by one period either way, and the truth
    similarity_threshold: float = 0.015  # RANSAC threshold of the 2D similarity, fraction of the width
    similarity_max_iters: int = 5000
    # a camera explains a recent point when an interest point within explain_px of its projection
    # matches its patch; None: 3 px in paper mode (two-view points scatter more), 1.5 px otherwise
    explain_px: float | None = None
    # a camera from the wide search replaces the near one's only when it explains this many
    # times its points (a period-shifted camera explains about as many; true winners 1.4-1.5x)
    wider_search_margin: float = 1.2
    # an epipolar chain with at least this many times ResectionConfig.min_inliers inliers is
    # trusted without consulting the prior
    trusted_chain_factor: float = 2.0
    recent_views: int = 3  # the points of the last few registered views are the ones projected

    def __post_init__(self) -> None:
        _as_tuple(self, "radius_fractions")
        _as_tuple(self, "pairings_per_point")
        _positive(self, "similarity_threshold", "trusted_chain_factor")
        _whole(self, "similarity_max_iters", "hypotheses_per_search", "recent_views")
        _in_range(self, "min_zncc", -1.0, 1.0)
        if not self.wider_search_margin >= 1.0:
            raise ValueError(f"MotionPriorConfig.wider_search_margin must be >= 1, got {self.wider_search_margin!r}")
        if not self.radius_fractions or not all(0 < r <= 1 for r in self.radius_fractions):
            raise ValueError(f"MotionPriorConfig.radius_fractions must be fractions in (0, 1], got {self.radius_fractions}")
        if not self.pairings_per_point or not all(isinstance(n, numbers.Integral) and n >= 1
                                                  for n in self.pairings_per_point):
            raise ValueError(f"MotionPriorConfig.pairings_per_point must be whole numbers >= 1, got {self.pairings_per_point}")
        if self.explain_px is not None:
            _positive(self, "explain_px")


@dataclass(frozen=True)
class TrackingConfig:
    """Accurate mode: points followed into more views by projection + patch alignment (COLMAP
    and ORB-SLAM search by projection), and new points checked in a third view."""

    # unaligned ZNCC a tracked point must reach at its prediction before the ~20x dearer
    # alignment runs (occluded points fail it)
    first_look_zncc: float = 0.3
    # a tracked position this close to an interest point standing for another 3D point is that
    # point, not this one
    min_distance_to_other_px: float = 1.0
    # a tracked position is kept when the aligned patches score above min_aligned_zncc (the
    # matcher's localisation check) and it lies within max_shift_px of the projection (the
    # resection's inlier threshold: the camera is that good)
    min_aligned_zncc: float = 0.9
    max_shift_px: float = 2.0
    # three-view points (repeated patterns): pairs within the epipolar band and above this ZNCC,
    # kept when a third view has a matching interest point within max_px of the projection
    three_view_min_zncc: float = 0.7
    three_view_max_px: float = 1.5

    def __post_init__(self) -> None:
        _in_range(self, "first_look_zncc", -1.0, 1.0)
        _in_range(self, "three_view_min_zncc", -1.0, 1.0)
        _in_range(self, "min_aligned_zncc", -1.0, 1.0)
        _positive(self, "min_distance_to_other_px", "three_view_max_px", "max_shift_px")


@dataclass(frozen=True)
class LoopClosureConfig:
    """Accurate mode: the last views matched against the first ones, tracks linked or merged,
    then a global BA."""

    span: int = 3  # the last `span` registered views against the first `span`
    min_matches: int = 20  # fewer matches between two views: no evidence of a shared point
    max_axis_angle_deg: float = 60.0  # views looking more apart than this share too little to match
    # the same physical point reconstructed twice lies within this fraction of its depth after
    # the drift of a ring (the box ring: < 1 %)
    merge_distance: float = 0.02
    # a link is accepted within this multiple of ResectionConfig.ransac_threshold_px (the drift
    # has not been adjusted away yet)
    link_threshold_factor: float = 4.0

    def __post_init__(self) -> None:
        _whole(self, "span", "min_matches")
        _positive(self, "merge_distance", "link_threshold_factor")
        _in_range(self, "max_axis_angle_deg", 0.0, 180.0)


@dataclass(frozen=True)
class VideoConfig:
    """Keyframes of a walk filmed as a video (:mod:`stereoseed.io.video`)."""

    # a keyframe once the tracked points moved by this fraction of the image width (median) since
    # the last one: the matcher searches 25 % of the width (paper), so consecutive keyframes stay
    # well inside its window while the parallax grows (about 5-10 degrees of a walk around an
    # object at a few object sizes)
    keyframe_motion: float = 0.08
    # or sooner, when fewer than this fraction of the points tracked since the last keyframe are
    # still tracked (a fast turn, an occlusion): the next keyframe must still share points
    min_tracked_fraction: float = 0.5
    # the keyframe is the sharpest (variance of the Laplacian, Pech-Pacheco et al. 2000) of the
    # last frames past 3/4 of the motion: a blurred frame loses its interest points
    sharpest_of: int = 6
    tracked_points: int = 400  # corners tracked by pyramidal Lucas-Kanade (Shi-Tomasi 1994)
    tracking_width: int = 640  # px: frames are tracked at most this wide (speed; keyframes stay full size)

    def __post_init__(self) -> None:
        if not 0.0 < self.keyframe_motion < 0.25:
            raise ValueError(f"VideoConfig.keyframe_motion must be in (0, 0.25) (the matcher's window), "
                             f"got {self.keyframe_motion!r}")
        if not 0.0 < self.min_tracked_fraction < 1.0:
            raise ValueError(f"VideoConfig.min_tracked_fraction must be in (0, 1), got {self.min_tracked_fraction!r}")
        _whole(self, "sharpest_of", "tracked_points", "tracking_width")
        _positive(self, "sharpest_of", "tracked_points", "tracking_width")


@dataclass(frozen=True)
class PipelineConfig:
    # "paper": 2-view points, 11-DOF moving camera, 3-image local BA (paper §4.2-4.3).
    # "accurate": multi-view tracks, constrained moving camera, wider BA window (Mouragnon et al.
    # 2006 for the windowed local BA). The two are strategies of stereoseed.sfm.modes.
    mode: str = "accurate"
    # None: "free" (paper) / "focal" (accurate: the calibrated second camera, only its zoom
    # changes); "fixed": no zoom at all (see hold_unzoomed for the accurate mode's own decision)
    camera_model: str | None = None
    # the last `window` cameras are free in the accurate mode's local BA; None: 3 (accurate) / 1
    # (paper: eq. 12 frees P_k alone, whatever the window)
    window: int | None = None
    # "local": local BA after each insertion; "global": global BA after each insertion; "final":
    # local + one global BA at the end. None: "local" in paper mode (the paper), "final" in
    # accurate mode (as COLMAP ends: an open sequence drifts slowly along its chain of windows)
    ba: str | None = None
    min_chained_points: int = 6  # paper: N >= 6 3D-2D pairs for the DLT
    retriangulate: bool = True  # accurate mode: re-triangulate a point from its whole track when it grows
    # accurate mode, "focal" model: when no image's resection found a zoom, the final global BA
    # holds every image at the calibrated camera's intrinsics (a free focal length per image only
    # trades against the depth)
    hold_unzoomed: bool = True
    loop_closure: bool = True  # accurate mode: match the last images against the first ones
    # After each BA, observations beyond outlier_factor x the median reprojection error (~3.4
    # sigma: the norm of 2-D Gaussian noise has median 1.18 sigma), never below outlier_floor_px,
    # are dropped. None: 4.0 in accurate mode, 0 (off) in paper mode; observations beyond
    # outlier_max_px always go.
    outlier_factor: float | None = None
    outlier_floor_px: float = 0.25
    outlier_max_px: float = 4.0  # always dropped: 2 x TriangulationConfig.max_reprojection_px
    # a resected camera whose focal length changed by more than this factor since the previous
    # image is refused (a hand-held zoom between two shots does not; a camera fitted to wrong
    # correspondences often does)
    max_zoom_step: float = 1.5
    # exports leave out a point farther from the scene's median point than this many times the
    # cameras' median distance to it (nearly parallel rays put points metres away from the object)
    far_point_factor: float = 5.0
    # The calibrated pair must prove it belongs to its two images: of their matches found without
    # the calibration (robust F), at least this fraction must lie within the epipolar band of the
    # calibrated geometry (measured: 100 % on the synthetic box, templeSparseRing and
    # dinoSparseRing; swapped cameras, swapped or identical images 2-56 %). Checked when the
    # images give at least pair_check_min_matches such matches (repeated patterns give none).
    pair_min_consistent: float = 0.8
    pair_check_min_matches: int = 20

    def __post_init__(self) -> None:
        _one_of(self, "mode", MODES)
        _one_of(self, "camera_model", CAMERA_MODELS, optional=True)
        _one_of(self, "ba", BA_POLICIES, optional=True)
        if self.window is not None:
            _whole(self, "window")
        _whole(self, "min_chained_points", minimum=6)  # the DLT needs 6 points
        if not self.max_zoom_step > 1.0:
            raise ValueError(f"PipelineConfig.max_zoom_step must be > 1 (a factor either way), got {self.max_zoom_step!r}")
        _positive(self, "outlier_max_px", "far_point_factor")
        _in_range(self, "pair_min_consistent", 0.0, 1.0)
        _whole(self, "pair_check_min_matches")
        if self.outlier_factor is not None and self.outlier_factor < 0:
            raise ValueError(f"PipelineConfig.outlier_factor must be >= 0 (0: off), got {self.outlier_factor}")
        if self.outlier_floor_px < 0:
            raise ValueError(f"PipelineConfig.outlier_floor_px must be >= 0, got {self.outlier_floor_px}")

    def resolved(self) -> "PipelineConfig":
        """The same configuration with every None (mode-dependent default) replaced by its value."""
        paper = self.mode == "paper"
        return dataclasses.replace(
            self, camera_model=CameraModel(self.camera_model or (CameraModel.FREE if paper else CameraModel.FOCAL)),
            window=self.window or (1 if paper else 3), ba=self.ba or ("local" if paper else "final"),
            outlier_factor=self.outlier_factor if self.outlier_factor is not None else (0.0 if paper else 4.0))

    def resolved_model(self) -> str:
        return self.resolved().camera_model

    def resolved_window(self) -> int:
        return self.resolved().window

    def resolved_ba(self) -> str:
        return self.resolved().ba

    def resolved_outlier_factor(self) -> float | None:
        factor = self.resolved().outlier_factor
        return factor if factor > 0 else None


@dataclass(frozen=True)
class Config:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    resection: ResectionConfig = field(default_factory=ResectionConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    propagation: PropagationConfig = field(default_factory=PropagationConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    motion_prior: MotionPriorConfig = field(default_factory=MotionPriorConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    quasi_dense: QuasiDenseConfig = field(default_factory=QuasiDenseConfig)
    video: VideoConfig = field(default_factory=VideoConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if not isinstance(getattr(self, f.name), f.default_factory):
                raise ValueError(f"Config.{f.name} must be a {f.default_factory.__name__}, "
                                 f"got {type(getattr(self, f.name)).__name__}")

    def resolve(self) -> "ResolvedConfig":
        """The configuration a run uses: the mode-dependent defaults (None) filled in, once (a
        :class:`ResolvedConfig` resolves to itself)."""
        pipeline = self.pipeline.resolved()
        prior = self.motion_prior
        if prior.explain_px is None:
            prior = dataclasses.replace(prior, explain_px=3.0 if pipeline.mode == "paper" else 1.5)
        sections = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return ResolvedConfig(**{**sections, "pipeline": pipeline, "motion_prior": prior})

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration as a JSON-able dict (what report.json records)."""
        return dataclasses.asdict(self.resolve())

    def replace(self, **sections: Any) -> "Config":
        """Copy with some stages' fields replaced: ``cfg.replace(matching={"min_zncc": 0.7})``."""
        updates = {}
        for name, values in sections.items():
            current = getattr(self, name)
            updates[name] = dataclasses.replace(current, **values) if isinstance(values, dict) else values
        return dataclasses.replace(self, **updates)


@dataclass(frozen=True)
class ResolvedConfig(Config):
    """A :class:`Config` with every mode-dependent default filled in: what a run's steps read.
    The public entry points resolve the configuration they are given once; the steps below them
    take this type and do not resolve again."""

    def resolve(self) -> "ResolvedConfig":
        return self

    def replace(self, **sections: Any) -> "ResolvedConfig":
        """Copy with some stages' fields replaced, still resolved (a field set to None takes its
        mode's default again)."""
        plain = Config(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        return plain.replace(**sections).resolve()
