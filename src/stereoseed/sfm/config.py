"""The mapper's settings: the mode and its defaults, registration (motion prior, quasi-dense),
tracking, loop closure, outlier removal and the pair check (:mod:`stereoseed.sfm`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass

from stereoseed.geometry.camera_model import MODELS, CameraModel
from stereoseed.validation import positive, whole, as_tuple, in_range, one_of

__all__ = ["TrustConfig", "ModeDefaults", "MODE_DEFAULTS", "RegistrationConfig", "OutlierConfig", "PairCheckConfig", 'QuasiDenseConfig', 'MotionPriorConfig', 'TrackingConfig', 'LoopClosureConfig', 'PipelineConfig']


MODES = ("paper", "accurate")
BA_POLICIES = ("local", "global", "final")
CAMERA_MODELS = MODELS


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
    # epipolar geometry does on these matches), and never below f_threshold_px. Over the 23 real
    # walks, as published and from JPEG q90 copies (docs/benchmarks.md, "The quasi-dense camera's
    # limit"): right cameras at 0.75-2.16 times the floor where the factor decides, wrong ones at
    # 2.61 (across 7 views not placed) and 3.8 and more; dinoSparseRing's wrong cameras (80-280 mm
    # off) had measured 2.4 and more before. 2.0 refused right cameras at 2.04 and 2.16 (0.3 and
    # 0.6 % off once taken), and with each every later image of the walk.
    camera_epipolar_factor: float = 2.25
    # an ambiguous choice's flag is lifted only when every rival camera lies this many times
    # farther from the propagated matches' epipolar geometry than the winner
    rival_epipolar_factor: float = 2.0
    # Images whose longer side exceeds this many pixels are brought down to it for the seeds and
    # the propagation (the matches are mapped back to the photos' pixels; 0: never): a 24-megapixel
    # pair's propagation held 2.8 GB, two at once (the candidate's and the previous pair's) 10 GB.
    # 3072 x 2048 (a 6-megapixel pair, 0.75 GB) is the largest the sets with ground truth have.
    max_side: int = 3072

    def __post_init__(self) -> None:
        if self.weak_chain_inliers is not None:
            whole(self, "weak_chain_inliers")
        whole(self, "grid_cell_px", "f_max_iters")
        whole(self, "max_side", minimum=0)
        in_range(self, "sift_ratio", 0.0, 1.0)
        in_range(self, "f_confidence", 0.0, 1.0)
        positive(self, "f_threshold_px", "chain_epipolar_px")
        in_range(self, "zoom_epipolar_ratio", 0.0, 1.0)
        for name, why in (("camera_epipolar_factor", "the robust F is the floor"),
                          ("rival_epipolar_factor", "a rival at least as far as the winner")):
            if not getattr(self, name) >= 1.0:
                raise ValueError(f"QuasiDenseConfig.{name} must be >= 1 ({why}), got {getattr(self, name)!r}")


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
        as_tuple(self, "radius_fractions")
        as_tuple(self, "pairings_per_point")
        positive(self, "similarity_threshold", "trusted_chain_factor")
        whole(self, "similarity_max_iters", "hypotheses_per_search", "recent_views")
        in_range(self, "min_zncc", -1.0, 1.0)
        if not self.wider_search_margin >= 1.0:
            raise ValueError(f"MotionPriorConfig.wider_search_margin must be >= 1, got {self.wider_search_margin!r}")
        if not self.radius_fractions or not all(0 < r <= 1 for r in self.radius_fractions):
            raise ValueError(f"MotionPriorConfig.radius_fractions must be fractions in (0, 1], got {self.radius_fractions}")
        if not self.pairings_per_point or not all(isinstance(n, numbers.Integral) and n >= 1
                                                  for n in self.pairings_per_point):
            raise ValueError(f"MotionPriorConfig.pairings_per_point must be whole numbers >= 1, got {self.pairings_per_point}")
        if self.explain_px is not None:
            positive(self, "explain_px")


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
        in_range(self, "first_look_zncc", -1.0, 1.0)
        in_range(self, "three_view_min_zncc", -1.0, 1.0)
        in_range(self, "min_aligned_zncc", -1.0, 1.0)
        positive(self, "min_distance_to_other_px", "three_view_max_px", "max_shift_px")


@dataclass(frozen=True)
class LoopClosureConfig:
    """Accurate mode: the last views matched against the first ones, tracks linked or merged,
    then a global BA; the gap between the two ends measured and judged at the end of the run
    (:func:`stereoseed.sfm.loop_closure.judge_loop`)."""

    span: int = 3  # the last `span` registered views against the first `span`
    min_matches: int = 20  # fewer matches between two views: no evidence of a shared point
    max_axis_angle_deg: float = 60.0  # views looking more apart than this share too little to match
    # the same physical point reconstructed twice lies within this fraction of its depth after
    # the drift of a ring (the box ring: < 1 %)
    merge_distance: float = 0.02
    # a link is accepted within this multiple of ResectionConfig.ransac_threshold_px (the drift
    # has not been adjusted away yet)
    link_threshold_factor: float = 4.0
    # The loop is closed when the gap measured between its ends is within this many of its
    # combined 1-sigma (the two end cameras' position sigmas and the gap's own standard error):
    # the norm of a 3-D Gaussian error exceeds 3 of its sigmas by chance in ~3 % of runs (the
    # trust module's 3-sigma bound likewise)
    gap_sigmas: float = 3.0
    # fewer first/last points measured between two end views: the gap's median rests on a
    # handful of matches, which a few wrong ones can set; such a pair is not evidence either way
    min_gap_points: int = 20
    # a pair of end views is a loop's ends when the walk between them is at least this many times
    # their straight distance: a ring's ends are one or two steps apart after the whole ring
    # (16 views: 6-14 times), while no walk along an arc of less than ~260 degrees comes to 3
    # (a half circle: pi/2; Strecha's fountain, facing one wall: 1.1)
    min_detour: float = 3.0

    def __post_init__(self) -> None:
        whole(self, "span", "min_matches", "min_gap_points")
        positive(self, "merge_distance", "link_threshold_factor", "gap_sigmas", "min_detour")
        in_range(self, "max_axis_angle_deg", 0.0, 180.0)


@dataclass(frozen=True)
class ModeDefaults:
    """What a mode sets where the user left a field at None (:class:`stereoseed.sfm.modes.Mode`
    reads its own): the camera model of the moving camera, the local BA's window, the BA policy,
    the outlier factor (0: off) and the motion prior's explain radius (px)."""

    camera_model: CameraModel
    window: int
    ba: str
    outlier_factor: float
    explain_px: float


MODE_DEFAULTS = {
    # the paper: an 11-DOF camera, eq. 12 frees P_k alone, a local BA after each insertion, no
    # outlier removal beyond the hard limit; its motion prior tolerates its two-view points' noise
    "paper": ModeDefaults(CameraModel.FREE, 1, "local", 0.0, 3.0),
    # ours: the calibrated second camera whose zoom only changes, a window of 3 (Mouragnon et al.
    # 2006), a final global BA as COLMAP ends (an open sequence drifts along its chain of
    # windows), observations beyond ~3.4 sigma dropped (the norm of 2-D Gaussian noise has
    # median 1.18 sigma)
    "accurate": ModeDefaults(CameraModel.FOCAL, 3, "final", 4.0, 1.5),
}


@dataclass(frozen=True)
class PipelineConfig:
    # "paper": 2-view points, 11-DOF moving camera, 3-image local BA (paper §4.2-4.3).
    # "accurate": multi-view tracks, constrained moving camera, wider BA window (Mouragnon et al.
    # 2006 for the windowed local BA). The two are strategies of stereoseed.sfm.modes.
    mode: str = "accurate"
    # None: the mode's (MODE_DEFAULTS); "fixed": no zoom at all (see hold_unzoomed for the
    # accurate mode's own decision)
    camera_model: str | None = None
    # the last `window` cameras are free in the accurate mode's local BA; None: the mode's
    # (the paper's eq. 12 frees P_k alone, whatever the window)
    window: int | None = None
    # "local": local BA after each insertion; "global": global BA after each insertion; "final":
    # local + one global BA at the end. None: the mode's
    ba: str | None = None
    retriangulate: bool = True  # accurate mode: re-triangulate a point from its whole track when it grows
    # accurate mode, "focal" model: when no image's resection found a zoom, the final global BA
    # holds every image at the calibrated camera's intrinsics (a free focal length per image only
    # trades against the depth)
    hold_unzoomed: bool = True
    loop_closure: bool = True  # accurate mode: match the last images against the first ones
    # a rig walk: the rig's relative pose (its rotation and baseline direction; the baseline's
    # length keeps the scale) refined once in the final BA, shared by every station; off: held
    # as calibrated (a calibration from many shots is better than one walk's own estimate)
    refine_rig: bool = False

    def __post_init__(self) -> None:
        one_of(self, "mode", MODES)
        one_of(self, "camera_model", CAMERA_MODELS, optional=True)
        one_of(self, "ba", BA_POLICIES, optional=True)
        if self.window is not None:
            whole(self, "window")

    @property
    def defaults(self) -> ModeDefaults:
        return MODE_DEFAULTS[self.mode]

    def resolved(self) -> "PipelineConfig":
        """The same configuration with every None replaced by its mode's default."""
        d = self.defaults
        return dataclasses.replace(self, camera_model=CameraModel(self.camera_model or d.camera_model),
                                   window=self.window or d.window, ba=self.ba or d.ba)

    def resolved_model(self) -> CameraModel:
        return self.resolved().camera_model


@dataclass(frozen=True)
class RegistrationConfig:
    min_chained_points: int = 6  # paper: N >= 6 3D-2D pairs for the DLT
    # a resected camera whose focal length changed by more than this factor since the previous
    # image is refused (a hand-held zoom between two shots does not; a camera fitted to wrong
    # correspondences often does)
    max_zoom_step: float = 1.5
    # The walk's first zoom, asked for by the window's BA (by BIC), is taken where the window
    # measures the focal length to max_focal_sigma (relative, 1 sigma), or where it is
    # zoom_certain_sigmas of its own sigmas. Else the view keeps the calibrated setting and is
    # flagged uncertain: on a narrow view of a shallow object a zoom and a step along the optical
    # axis look alike to second order, and errors the model does not know (biased matches) then pass for a zoom with
    # a large BIC (the iid statistic counts them as evidence). The scale: spurious 4-9 % zooms of
    # the unzoomed dinoRing1-24 walks measured to 0.8-1.8 %, 4-10 sigmas; the real 1-19 % zoom
    # steps of the synthetic walks to 0.07-0.3 % at 640 px, 0.2-0.8 % (16-38 sigmas) at 320 px.
    max_focal_sigma: float = 0.004
    zoom_certain_sigmas: float = 12.0

    def __post_init__(self) -> None:
        whole(self, "min_chained_points", minimum=6)  # the DLT needs 6 points
        in_range(self, "max_focal_sigma", 0.0, 1.0)
        positive(self, "zoom_certain_sigmas")
        if not self.max_zoom_step > 1.0:
            raise ValueError(f"RegistrationConfig.max_zoom_step must be > 1 (a factor either way), "
                             f"got {self.max_zoom_step!r}")


@dataclass(frozen=True)
class OutlierConfig:
    # After each BA, observations beyond factor x the median reprojection error, never below
    # floor_px, are dropped. None: the mode's (0: off); observations beyond max_px always go.
    factor: float | None = None
    floor_px: float = 0.25
    max_px: float = 4.0  # always dropped: 2 x TriangulationConfig.max_reprojection_px

    def __post_init__(self) -> None:
        positive(self, "max_px")
        if self.factor is not None and self.factor < 0:
            raise ValueError(f"OutlierConfig.factor must be >= 0 (0: off), got {self.factor}")
        if self.floor_px < 0:
            raise ValueError(f"OutlierConfig.floor_px must be >= 0, got {self.floor_px}")

    def active_factor(self) -> float | None:
        """The factor in force (None: off); resolved configurations only."""
        return self.factor if self.factor else None


@dataclass(frozen=True)
class PairCheckConfig:
    # The calibrated pair must prove it belongs to its two images: of their matches found without
    # the calibration (robust F), at least this fraction must lie within the epipolar band of the
    # calibrated geometry (docs/mapper.md has the measurements). Checked when the images give at
    # least min_matches such matches (repeated patterns give none).
    min_consistent: float = 0.8
    min_matches: int = 20
    # A pair under min_consistent still stands when matching under its own epipolar geometry finds
    # at least this fraction of the robust F's matches: a robust F locked on a repeated pattern's
    # wrong period (the castle's 0014/0013: 77-78 % consistent, its own matching 0.99-1.04 times
    # as many, the two counts trading places with the JPEG quality). Calibrations of other images
    # (swapped cameras or images, another set's pair) find 0.03-0.85 times as many (docs/mapper.md).
    min_known_ratio: float = 0.9

    def __post_init__(self) -> None:
        in_range(self, "min_consistent", 0.0, 1.0)
        in_range(self, "min_known_ratio", 0.0, 1.0)
        whole(self, "min_matches")


@dataclass(frozen=True)
class TrustConfig:
    """When the run cannot vouch for a camera (docs/mapper.md, "Trust"). Each limit is relative to
    the scene, so a walk round a statuette and one along a building are judged alike."""

    # Registration: the motion prior's competing cameras are ambiguous (a repeated pattern matched
    # one period over) when the runner-up explains at least ambiguity_ratio of the winner's
    # points while standing farther than ambiguity_shift x the recent points' depth from it. A
    # camera one period off explains its own correspondences as well as the true one and loses
    # only the pattern's ends (within a factor 1.5: 0.67); an unrelated wrong camera explains
    # far fewer (0.3-0.4 of the winner's, docs/mapper.md). Cameras of one hypothesis family
    # stand a few per mille of the depth apart; a period of a facade's windows or a box's
    # squares is several per cent of it.
    ambiguity_ratio: float = 0.6
    ambiguity_shift: float = 0.02
    # After the final BA, a camera whose observations reproject worse than residual_factor x the
    # median camera's RMS (and worse than residual_floor_px) is contradicted by the others.
    residual_factor: float = 3.0
    residual_floor_px: float = 0.5
    # A camera whose 3-sigma position (its worst axis) exceeds 1 % of its median depth is not
    # determined well enough to build on (issue #47: a walk 1 % off is visibly wrong).
    max_position_sigma: float = 0.01 / 3
    # The cameras' uncertainty counts one observation per camera and square image cell of this
    # size (px): the matching's 11x11 ZNCC window (MatchingConfig.patch_size), so matches whose
    # windows overlap - the propagated matches, one per pixel - count as the correlated evidence
    # they are, not as thousands of independent ones (issue #47: the dino cameras placed by
    # propagated matches were 10-22 mm off with a stated sigma of 1-4 mm). None: every
    # observation independent.
    independent_cell_px: float | None = 11.0
    # The cameras' uncertainty is also measured from the residuals themselves, points grouped by
    # the spread_cell_px cell of their first view (a few correlation windows: propagated matches
    # share their errors that far), and the larger one reported (issue #47: "the covariance
    # reported as the larger of the model's and the measured spread"). On the real sets and walks
    # it raises the stated sigma by a median 1.10x (1.00-2.27x), at 11-128 px alike
    # (docs/benchmarks.md). None: the model's alone.
    spread_cell_px: float | None = 32.0
    # After the final BA, a camera must be tied to the model by at least this many observations
    # of points two other cameras also see (each pins it as a 3D-2D pair does; a two-view point
    # only moves with it); fewer and the BA cannot check where its registration put it (a view
    # registered on quasi-dense matches keeps only its sparse observations). None: the chain the
    # motion prior trusts, MotionPriorConfig.trusted_chain_factor x ResectionConfig.min_inliers.
    min_tied_observations: int | None = None
    # After the final BA, judge each camera the motion prior or the quasi-dense matches placed
    # again between its neighbours (stereoseed.sfm.hindsight): 0.1-0.25 s a camera judged; off
    # on a long weakly textured walk where that time matters more than the check.
    judge_between_neighbours: bool = True
    # Keep flagged cameras' observations in the model and their images in the dense stage.
    keep_flagged: bool = False

    def __post_init__(self) -> None:
        in_range(self, "ambiguity_ratio", 0.0, 1.0)
        positive(self, "ambiguity_shift", "residual_factor", "max_position_sigma")
        if self.independent_cell_px is not None:
            positive(self, "independent_cell_px")
        if self.spread_cell_px is not None:
            positive(self, "spread_cell_px")
        if self.min_tied_observations is not None:
            whole(self, "min_tied_observations")
        if self.residual_floor_px < 0:
            raise ValueError(f"TrustConfig.residual_floor_px must be >= 0, got {self.residual_floor_px}")
