"""The pair recipe: how the pipeline matches two images (:func:`match_pair`).

ZNCC candidates (:mod:`.zncc`), epipolar geometry (:mod:`.two_view`: the known F's band, or a
robust F then matching guided by it) and the localisation check (:mod:`.alignment`). Every
threshold comes from the one :class:`~stereoseed.config.MatchingConfig`; docs/matching.md says
what each step adds to the paper's recipe and what it was measured to give.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from stereoseed.matching.config import MatchingConfig
from stereoseed.features.harris import Features
from stereoseed.matching.alignment import PairCache, filter_localization
from stereoseed.matching.containers import Matches, PairMatches
from stereoseed.matching.two_view import filter_epipolar, filter_fundamental_ransac
from stereoseed.matching.zncc import match_zncc

__all__ = ["match_pair", "candidate_config"]

log = logging.getLogger(__name__)


def match_pair(
    f1: Features,
    f2: Features,
    config: MatchingConfig,
    F: np.ndarray | None = None,
    image_width: float | None = None,
    cache: PairCache | None = None,
) -> PairMatches:
    """Match two images: ZNCC candidates, epipolar geometry, localisation check.

    f1, f2: features of the two images (from :func:`stereoseed.features.harris.extract_features`, which
    keeps the grey images the localisation check needs); ``image_width`` (px, default f2's)
    scales ``config.search_radius``.

    * F (3, 3) known (both cameras calibrated): candidates restricted to the
      ``config.epipolar_band_px`` band *before* the best one is chosen (guided matching, ratio
      ``config.guided_max_ratio``), then the localisation check.
    * F None: candidates in the search window (ratio ``config.first_pass_ratio``, default none:
      a ratio test there starves RANSAC), localisation check, robust F
      (``config.ransac_*``, at least ``config.min_f_inliers`` inliers), then a second pass guided
      by the ``config.ransac_threshold_px`` band of that F, checked again and kept if it has at
      least as many matches as the RANSAC inliers.

    Candidates (:func:`~stereoseed.matching.zncc.match_zncc`): best ZNCC above
    ``config.candidate_min_zncc`` (not the paper's ``min_zncc``: the localisation check is the
    acceptance test here), mutual if ``config.mutual``, image-2 patches also resampled at
    ``config.scales``. Localisation check
    (:func:`~stereoseed.matching.alignment.filter_localization`): aligned position within
    ``config.max_shift_px`` of the detected point, aligned ZNCC > ``config.min_aligned_zncc``
    (pass ``config.relaxed()`` for the relaxed check); kept matches are scored by their aligned
    ZNCC. Skipped (logged, stats["localization"] says so) for Features without grey images.

    ``cache`` (:class:`PairCache` for (f1, f2)) spares the scores and alignments already
    computed for this pair, also across ``config`` and ``config.relaxed()``.

    Returns a :class:`PairMatches`: the matches (best score first; empty when no robust F was
    found), the F used or estimated (None when the robust estimate failed) and the counts per
    stage, stats["geometry"] being "known F", "robust F" or "robust F failed: <reason>".
    """
    localize = f1.gray is not None and f2.gray is not None
    stats: dict = {"features": [len(f1), len(f2)]}
    if not localize:
        log.info("localisation check skipped: Features without grey images (use extract_features)")
        stats["localization"] = "skipped: Features without grey images"
    first_pass = candidate_config(config, config.first_pass_ratio)
    guided = candidate_config(config, config.guided_max_ratio)

    def check(m: Matches) -> Matches:
        return filter_localization(m, f1, f2, config, cache=cache) if localize else m

    def result(m: Matches, F: np.ndarray | None) -> PairMatches:
        stats["kept"] = len(m)
        return PairMatches(m, F, stats)

    if F is not None:
        F = np.asarray(F, np.float64)
        band = float(config.epipolar_band_px)
        stats["geometry"] = "known F"
        m = match_zncc(f1, f2, guided, image_width, F=F, band_px=band, multiscale=True, cache=cache)
        stats["candidates"] = len(m)
        return result(check(filter_epipolar(m, f1, f2, F, band)), F)

    m = match_zncc(f1, f2, first_pass, image_width, multiscale=True, cache=cache)
    stats["candidates"] = len(m)
    m = check(m)
    stats["localized"] = len(m)
    m, F, reason = filter_fundamental_ransac(m, f1, f2, config)
    stats["ransac_inliers"] = len(m)
    if F is None:
        log.debug("pair without a robust F: %s", reason)
        stats["geometry"] = f"robust F failed: {reason}"
        return result(m, None)
    stats["geometry"] = "robust F"
    band = float(config.ransac_threshold_px)
    mg = match_zncc(f1, f2, guided, image_width, F=F, band_px=band, multiscale=True, cache=cache)
    stats["guided_candidates"] = len(mg)
    mg = check(filter_epipolar(mg, f1, f2, F, band))
    # Guided matching should only add matches; if it does not, keep the RANSAC inliers.
    if len(mg) >= len(m):
        m = mg
    return result(m, F)


def candidate_config(config: MatchingConfig, max_ratio: float | None) -> MatchingConfig:
    """What :func:`match_zncc` sees for the recipe's candidates: ``candidate_min_zncc`` as its
    acceptance threshold and the given uniqueness ratio."""
    return dataclasses.replace(config, min_zncc=config.candidate_min_zncc, max_ratio=max_ratio)
