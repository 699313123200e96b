"""The matching stage's settings: ZNCC matching, alignment, two-view (:mod:`stereoseed.matching`)
and Lhuillier-Quan propagation (:mod:`stereoseed.matching.propagation`).

Every default states its source (see :mod:`stereoseed.config`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from stereoseed.validation import positive, in_range, one_of, whole

__all__ = ['MatchingConfig', 'PropagationConfig', 'OrderingConfig']


# a patch wider than this compares regions, not points (the paper's is 11 x 11), and no corner
# within half its width of an image's border can be matched: 101 still leaves most of 640 x 480
MAX_PATCH_SIZE = 101


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
            check(isinstance(v, int) and 0 < v <= MAX_PATCH_SIZE and v % 2 == 1,
                  f"{name} must be an odd positive integer up to {MAX_PATCH_SIZE}, got {v!r}")
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
        in_range(self, "min_zncc", -1.0, 1.0)
        positive(self, "neighbourhood", "epipolar_band_px")
        one_of(self, "subpixel_method", ("affine", "quadratic"))


@dataclass(frozen=True)
class OrderingConfig:
    # "auto": a folder's photos (their names' order is the file system's) are put in walk order;
    # a list is run as written (someone wrote that order). "images": any input is. Either way a
    # given order that the overlaps show to be a walk is kept. "as-given": never reordered.
    # (Folders only by default: matching every pair costs 1-3 s on a 14-image walk, a third of
    # the whole run the speed section times.)
    mode: str = "auto"
    # thumbnails' long side (px): SIFT needs a few hundred features per view (ORB found too few
    # on the temple's white plaster); a 24-megapixel photo is matched at a 1/8 of its size
    thumbnail_px: int = 640
    features: int = 1500  # SIFT features per thumbnail: about what the sparse matcher keeps per image
    ratio: float = 0.8  # Lowe's ratio test (IJCV 2004: 0.8 drops 90 % of false matches)
    ransac_px: float = 2.0  # the robust F's threshold on thumbnails (a pixel and a half of 640 px)
    # two thumbnails overlap when at least this many matches agree on one F: a robust F of 7-8
    # points with a few more to spare (a few hundred mutual ratio-tested matches put one or two
    # beyond the sample within 2 px by chance). The weak steps of real rings sit just above it
    # (templeSparseRing 13, dinoRing1-24 every 3rd 16).
    min_inliers: int = 12
    # Where SIFT finds too little to match (dark, weakly textured turntable objects: 5 of
    # dinoSparseRing's 15 steps have no overlap), neighbouring views still look alike: the
    # thumbnails' grey levels (long side appearance_px, blurred by one pixel) correlate best after
    # a shift of up to appearance_shift of their size (ZNCC of one's centre slid over the other).
    # A step's strength is its SIFT overlap plus appearance_weight x that correlation, so the
    # appearance only decides between steps SIFT cannot tell apart (a correlation is worth at most
    # appearance_weight matches). A step without SIFT overlap counts as supported when the
    # correlation reaches appearance_min: half the grey-level variance shared (the real rings'
    # neighbours without overlap correlate at 0.64-0.93; any two views of one object often at
    # 0.6-0.9, so this is a floor against unrelated photos, not a test of adjacency).
    appearance_px: int = 96
    appearance_shift: float = 0.15
    appearance_weight: float = 5.0
    appearance_min: float = 0.5
    # a given order is replaced only when the recovered walk's total overlap is this many times its
    # own (or the given order has a step without overlap): a walk in order is not second-guessed
    replace_factor: float = 1.25
    # every pair is matched (n^2 / 2, ~10 ms a pair on 640 px thumbnails): above this many images
    # (1770 pairs, about 20 s) the order is kept as given and the run says so
    max_images: int = 60

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "images", "as-given"):
            raise ValueError(f"OrderingConfig.mode must be 'auto', 'images' or 'as-given', got {self.mode!r}")
        whole(self, "thumbnail_px", "features", "min_inliers", "max_images", "appearance_px", minimum=8)
        positive(self, "ratio", "ransac_px", "replace_factor")
        in_range(self, "appearance_shift", 0.0, 0.45)
        in_range(self, "appearance_min", 0.0, 1.0)
        in_range(self, "appearance_weight", 0.0, 1e6)
        if not self.ratio < 1.0:
            raise ValueError(f"OrderingConfig.ratio must be < 1, got {self.ratio!r}")
