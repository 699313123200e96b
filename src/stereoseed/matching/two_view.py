"""Two-view epipolar geometry of matches: the epipolar band and a robust fundamental matrix.

Paper §4.1 step 4 and §4.2: false matches are removed by the epipolar constraint, with F from the
two calibrated cameras (:func:`filter_epipolar`, :func:`epipolar_band_mask` for all pairs at
once) or, when only the images are known, from a robust estimate (:func:`filter_fundamental_ransac`).
F is (3, 3) with ``x2^T F x1 = 0`` for pixels x1 of image 1 and x2 of image 2.
"""
from __future__ import annotations

import cv2
import numpy as np

from stereoseed.geometry.projection import epipolar_distances
from stereoseed.matching.config import MatchingConfig
from stereoseed.features.harris import Features
from stereoseed.matching.containers import Matches
from stereoseed.matching.zncc import candidate_mask

__all__ = ["epipolar_band_mask", "filter_epipolar", "filter_fundamental_ransac"]



def epipolar_band_mask(
    F: np.ndarray, x1: np.ndarray, x2: np.ndarray, band_px: float
) -> np.ndarray:
    """(N1, N2) bool: pairs of x1 (N1, 2) and x2 (N2, 2) within ``band_px`` of each other's
    epipolar line in both images.

    Same distance as :func:`stereoseed.geometry.projection.epipolar_distances` (max of both one-sided
    distances), for all pairs at once: the numerator |x2^T F x1| is shared, so the max distance
    is that numerator over the smaller of the two line normals.
    """
    return candidate_mask(x1, x2, np.inf, F, band_px)


def filter_epipolar(
    matches: Matches,
    kp1: Features | np.ndarray,
    kp2: Features | np.ndarray,
    F: np.ndarray,
    band_px: float,
) -> Matches:
    """Keep the matches within ``band_px`` of their epipolar lines in both images.

    F: (3, 3); kp1, kp2: Features or (N, 2) points.
    """
    if len(matches) == 0:
        return matches
    x1, x2 = matches.points(kp1, kp2)
    d = epipolar_distances(np.asarray(F, np.float64), x1, x2)
    return matches.subset(np.isfinite(d) & (d <= band_px))


def filter_fundamental_ransac(
    matches: Matches,
    kp1: Features | np.ndarray,
    kp2: Features | np.ndarray,
    config: MatchingConfig,
    *,
    method: int = cv2.USAC_MAGSAC,
) -> tuple[Matches, np.ndarray | None, str]:
    """Estimate F robustly and keep the matches consistent with it.

    method: an OpenCV robust method (``cv2.USAC_MAGSAC`` default, or ``cv2.FM_RANSAC``); threshold
    ``config.ransac_threshold_px``, confidence and iterations from ``config``; deterministic
    (USAC: seeded by ``config.seed``; FM_RANSAC: OpenCV seeds it with a constant). Up to
    ``config.ransac_runs`` runs (seeds seed, seed + 1, ...) until one has
    ``config.ransac_enough_inliers``, the F with the most inliers kept. Inliers are the matches
    within the threshold of their epipolar lines in both images
    (:func:`stereoseed.geometry.projection.epipolar_distances`), recomputed from the returned F.

    Returns (inlier Matches, F (3, 3) float64 of unit norm, "") or (empty Matches, None, why)
    when there are fewer than 8 matches, no estimate, or fewer than ``config.min_f_inliers``
    inliers.
    """
    if len(matches) < 8:
        return Matches.empty(), None, f"needs at least 8 matches, got {len(matches)}"
    x1, x2 = matches.points(kp1, kp2)
    # One robust run on a weak pair depends on its random samples; the best-supported of a few
    # runs takes most of the luck out, and a pair whose best run already has many inliers is not
    # weak. FM_RANSAC ignores the seed (see _robust_fundamental): one run is all it can give.
    runs = max(int(config.ransac_runs), 1) if method == cv2.USAC_MAGSAC else 1
    F, inl, error = None, np.zeros(len(matches), bool), None
    for run in range(runs):
        if inl.sum() >= config.ransac_enough_inliers:
            break
        try:
            F_run = _robust_fundamental(x1, x2, config, method, int(config.seed) + run)
        except cv2.error as exc:  # degenerate configurations make some estimators throw
            error = exc
            continue
        if F_run is None or F_run.shape[0] < 3 or not np.all(np.isfinite(F_run)) or np.linalg.norm(F_run[:3]) == 0:
            continue
        F_run = np.asarray(F_run[:3], np.float64) / np.linalg.norm(F_run[:3])
        d = epipolar_distances(F_run, x1, x2)
        inl_run = np.isfinite(d) & (d <= config.ransac_threshold_px)
        if F is None or inl_run.sum() > inl.sum():
            F, inl = F_run, inl_run
    if F is None:
        return Matches.empty(), None, (f"OpenCV failed: {error}" if error is not None else "no model found")
    if inl.sum() < config.min_f_inliers:
        return (Matches.empty(), None,
                f"only {int(inl.sum())} inliers (< {config.min_f_inliers}): rejected")
    return matches.subset(inl), F, ""


def _robust_fundamental(x1: np.ndarray, x2: np.ndarray, config: MatchingConfig, method: int,
                        seed: int) -> np.ndarray | None:
    """One OpenCV robust F estimate from pixels x1, x2 (N, 2), its randomness fixed by seed
    (USAC methods only)."""
    if method == cv2.USAC_MAGSAC:
        # The USAC flags ignore cv2.setRNGSeed (their generator state defaults to 0); the
        # parameter object is the USAC_MAGSAC preset with the seed made explicit.
        params = cv2.UsacParams()
        params.threshold = float(config.ransac_threshold_px)
        params.confidence = float(config.ransac_confidence)
        params.maxIterations = int(config.ransac_max_iters)
        params.sampler = cv2.SAMPLING_UNIFORM
        params.score = cv2.SCORE_METHOD_MAGSAC
        params.loMethod = cv2.LOCAL_OPTIM_SIGMA
        params.final_polisher = cv2.MAGSAC
        params.randomGeneratorState = seed
        return cv2.findFundamentalMat(x1, x2, params)[0]
    # The other methods need no global cv2.setRNGSeed: OpenCV's RANSAC/LMeDS point-set
    # registrator draws its samples from its own RNG seeded with a constant on every call
    # (calib3d ptsetreg.cpp, "RNG rng((uint64)-1)"), so they are deterministic and ignore seed
    # (checked on OpenCV 5.0: identical F and mask whatever the global RNG state).
    return cv2.findFundamentalMat(x1, x2, method, float(config.ransac_threshold_px),
                                  float(config.ransac_confidence), int(config.ransac_max_iters))[0]
