"""The calibration's settings: when a view is dropped, when a camera is refused, how robust the
fit is. Every default states its reason; nothing is tuned to one target or camera."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereoseed.validation import in_range, positive

__all__ = ["CalibrationConfig", "camera_problems", "chi2_quantile_4"]


@dataclass(frozen=True)
class CalibrationConfig:
    # --- a physical camera (checked on every calibrated camera; a camera outside these is
    # refused with the reason: what the data could not pin down came out as nonsense) ---
    # Square pixels are the rule; sensors with non-square pixels differ by a few %, and one view
    # of a target that leaves the focal lengths undetermined drifts by tens of % (1054 vs 2743 px).
    max_aspect_difference: float = 0.05  # |fy / fx - 1|
    # The principal point lies near the image's centre on every camera lens short of a shift
    # lens; a principal point outside the middle half of the frame (a quarter of the width or
    # height from an edge) is a sign that the views did not determine it.
    principal_point_region: float = 0.5  # the central share of the width and height it must lie in
    # Decentring (tangential) terms of real lenses are ~1e-3; 0.05 moves a corner pixel by tens
    # of pixels: the sign of a fit that traded them against the pose.
    max_tangential: float = 0.05  # |p1|, |p2|

    # --- the fit ---
    # Huber's threshold on a corner's 2D error, in robust standard deviations of the corners'
    # errors (3: a Gaussian corner is an outlier 1 % of the time) and at least this many pixels
    # (corners of sharp photos agree with OpenCV's to ~0.15 px; below 0.5 px the loss would
    # treat ordinary corners as outliers).
    huber_sigmas: float = 3.0
    huber_min_px: float = 0.5
    # A view whose RMS exceeds this many times the median view's (and view_outlier_min_px) is
    # dropped, its reason reported: another camera's image, a moved lens, a target that moved
    # while the rig's two shutters closed. Blur alone makes a view 1.5-3 times worse.
    view_outlier_factor: float = 5.0
    # A corner left at OpenCV's position (its saddle fit failed: a defocused face) is 0.2-1 px
    # off on renders where fitted corners are within 0.06 px (detection.py). Its error scale is
    # measured where both kinds are numerous enough; with fewer it is taken as this many times
    # the fitted corners': 8 such corners among 163, weighed like fitted ones, pulled a rendered
    # camera's whole-frame p95 error from 0.03 to 0.26 px (docs/benchmarks.md, lens calibration).
    unrefined_sigma_ratio: float = 10.0
    view_outlier_min_px: float = 2.0
    # Views of a flat target one camera needs for its intrinsics (Zhang: 2 constraints per view
    # on 4 intrinsics, and views at different angles); with fewer it needs known intrinsics.
    min_flat_views: int = 3
    # The faces' poses are estimated only where the photos show them off their nominal place:
    # the refined fit's BIC must be lower than the nominal one's by this much (strong evidence,
    # Kass & Raftery 1995, as ResectionConfig.zoom_evidence_bic). A well-made target seen in a
    # few views keeps its geometry instead of trading it against the intrinsics.
    refine_evidence_bic: float = 6.0
    # The whole model (faces rigid on one target) is checked against each camera's faces taken
    # one by one (each face its own pose per view: no assumption on how the faces sit): if the
    # two fits' fx, fy, cx, cy differ by more than chance allows (chi-square with 4 degrees of
    # freedom over the one-by-one fit's covariance, beyond its 0.999 quantile), the target is
    # not the rigid body the model assumes (a face bent, the cube flexed) and that camera keeps
    # the one-by-one intrinsics (a Hausman-style specification test). None: no test, the whole
    # model's intrinsics whatever they are.
    consistency_quantile: float | None = 0.999
    max_iterations: int = 200

    # --- a fixed rig (--rig): its shots checked against each other, its pose against its evidence ---
    # Two views taken together give the rig's relative pose from each camera's own fit of its
    # view: within ~2.5 degrees and 8 % of the baseline on the real cube's views of one face with
    # a 21-degree lens (0.1-0.5 degree with two faces or more); a photo paired with another
    # shot's is off by the target's turn between the two shots, tens of degrees. Shots agree
    # when within both of these of each other.
    rig_shot_agreement_deg: float = 5.0
    rig_shot_agreement_share: float = 0.25  # of the baseline
    # Fewer shots than this share agreeing with one relative pose: no fixed pair took them
    # together in the order given (a majority is what a rig with a few bad shots still has).
    rig_min_agreeing_share: float = 0.5
    # The rig's stated uncertainty, in standard errors of the jackknife over shots (the
    # intrinsics re-estimated with each shot left out): 3 covers what a normal error exceeds
    # 0.3 % of the time, and the jackknife's own uncertainty from a dozen shots.
    rig_uncertainty_sigmas: float = 3.0
    # Above these the rig is reported as weakly determined (a warning naming the intrinsics
    # that limit it; refused with strict): 0.3 degree moves a point 5 mm at 1 m, 1 % of the
    # baseline is 1 % of every distance the pair measures.
    rig_warn_rotation_deg: float = 0.3
    rig_warn_baseline_share: float = 0.01

    # --- what the user is told (not fatal unless max_rms_px is given) ---
    # a camera's RMS above this is reported as a warning: sharp corners on an accurate target
    # reproject within ~0.5 px, 1-2 px is a blurred view or an imperfect target
    warn_rms_px: float = 1.5
    max_rms_px: float | None = None  # above this the calibration is refused (--max-rms)
    # a result whose own checks disagree (a rig weakly determined, its pose against its shots'
    # evidence) is refused instead of written with a warning (--strict)
    strict: bool = False

    def __post_init__(self) -> None:
        positive(self, "max_aspect_difference", "max_tangential", "huber_sigmas", "huber_min_px",
                 "view_outlier_factor", "view_outlier_min_px", "unrefined_sigma_ratio", "warn_rms_px", "max_iterations", "min_flat_views",
                 "refine_evidence_bic", "rig_shot_agreement_deg", "rig_shot_agreement_share", "rig_uncertainty_sigmas",
                 "rig_warn_rotation_deg", "rig_warn_baseline_share")
        in_range(self, "rig_min_agreeing_share", 0.0, 1.0)
        in_range(self, "principal_point_region", 0.0, 1.0)
        if self.consistency_quantile is not None:
            in_range(self, "consistency_quantile", 0.5, 0.999999)
        if self.max_rms_px is not None and not self.max_rms_px > 0:
            raise ValueError(f"CalibrationConfig.max_rms_px must be > 0 or None, got {self.max_rms_px!r}")


def camera_problems(K: np.ndarray, lens: np.ndarray, size: tuple[int, int] | None,
                    cfg: CalibrationConfig = CalibrationConfig()) -> list[str]:
    """Why the camera K, lens cannot be a physical camera (empty: it can)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = []
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(lens)) and fx > 0 and fy > 0):
        return [f"the focal lengths came out as ({fx:.4g}, {fy:.4g}) px"]
    if abs(fy / fx - 1) > cfg.max_aspect_difference:
        out.append(f"f = ({fx:.0f}, {fy:.0f}) px: fx and fy differ by {100 * abs(fy / fx - 1):.0f} % "
                   f"(a physical camera: within {100 * cfg.max_aspect_difference:.0f} %)")
    if size is not None:
        w, h = size
        lo, hi = (1 - cfg.principal_point_region) / 2, (1 + cfg.principal_point_region) / 2
        if not (lo * w <= cx <= hi * w and lo * h <= cy <= hi * h):
            out.append(f"principal point ({cx:.0f}, {cy:.0f}) outside the middle {100 * cfg.principal_point_region:.0f} % "
                       f"of the {w}x{h} frame")
    if size is not None and not _monotonic(K, lens, size):
        out.append(f"the lens (k1 k2 k3 = {lens[0]:.3g}, {lens[1]:.3g}, {lens[4]:.3g}) folds the image back before "
                   "its corners: no lens does")
    p1, p2 = lens[2], lens[3]
    if max(abs(p1), abs(p2)) > cfg.max_tangential:
        out.append(f"tangential distortion p1 = {p1:.3g}, p2 = {p2:.3g} (a physical lens: within "
                   f"{cfg.max_tangential:g})")
    return out


def _monotonic(K: np.ndarray, lens: np.ndarray, size: tuple[int, int]) -> bool:
    """Whether the radial distortion r (1 + k1 r^2 + k2 r^4 + k3 r^6) keeps growing out to the
    frame's farthest corner: past its turning point two rays land on one pixel."""
    corners = np.array([[0, 0], [size[0], 0], [0, size[1]], [size[0], size[1]]], float)
    r_max = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0], (corners[:, 1] - K[1, 2]) / K[1, 1])))
    r2 = np.linspace(0.0, r_max, 200) ** 2
    k1, k2, k3 = lens[0], lens[1], lens[4]
    slope = 1 + 3 * k1 * r2 + 5 * k2 * r2 ** 2 + 7 * k3 * r2 ** 3  # d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6)
    return bool(np.all(slope > 0))


def chi2_quantile_4(p: float) -> float:
    """The p-quantile of the chi-square distribution with 4 degrees of freedom, whose CDF is
    1 - exp(-x / 2) (1 + x / 2): bisection to 1e-9 (18.467 at 0.999)."""
    low, high = 0.0, 1000.0
    while high - low > 1e-9 * max(high, 1.0):
        x = (low + high) / 2
        low, high = (x, high) if 1 - np.exp(-x / 2) * (1 + x / 2) < p else (low, x)
    return (low + high) / 2
