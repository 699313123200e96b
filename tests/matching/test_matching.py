"""ZNCC matching, epipolar filters, robust F, localisation check, the pair recipe and its
configuration (stereoseed.matching, MatchingConfig).

The quality tests measure kept matches against the exact correspondences of the synthetic box
(stereoseed.synthetic.scene): the world point seen at a keypoint of image i, projected into image j.
"""
from __future__ import annotations

import dataclasses
import logging
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from stereoseed.geometry.projection import (
    decompose_projection,
    epipolar_distances,
    fundamental_from_projections,
    project,
)
from stereoseed.config import FeatureConfig, MatchingConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import Features, describe, extract_features
from stereoseed.matching import alignment
from stereoseed.matching.alignment import PairCache, align_matches, filter_localization, refine_features
from stereoseed.matching.containers import Matches, PairMatches
from stereoseed.matching.pair import match_pair
from stereoseed.matching.two_view import epipolar_band_mask, filter_epipolar, filter_fundamental_ransac
from stereoseed.matching.zncc import match_zncc, zncc_matrix
from stereoseed.output.visualize import draw_matches

from geometry_helpers import band_noise


# --- helpers ---------------------------------------------------------------------------------
def warped_pair(H: np.ndarray, shape=(240, 320), seed: int = 0):
    """A texture and its copy warped by homography H (image 1 -> image 2), as uint8."""
    h, w = shape
    img1 = band_noise(shape, seed)
    img2 = cv2.warpPerspective(img1, H, (w, h), flags=cv2.INTER_CUBIC,
                               borderMode=cv2.BORDER_REFLECT)

    def u8(img: np.ndarray) -> np.ndarray:
        return (np.clip(img, 0, 1) * 255).round().astype(np.uint8)

    return u8(img1), u8(img2)


def apply_h(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(x.reshape(-1, 1, 2), H).reshape(-1, 2)


def accuracy(scene, i, j, f1, f2, m: Matches) -> dict:
    x1, x2 = m.points(f1, f2)
    xt, ok = scene.true_match(i, j, x1)
    err = np.linalg.norm(xt - x2, axis=1)[ok]
    return {
        "kept": len(m),
        "evaluated": int(ok.sum()),
        "within_1px": float(np.mean(err < 1.0)) if len(err) else float("nan"),
        "within_3px": float(np.mean(err < 3.0)) if len(err) else float("nan"),
        "median_px": float(np.median(err)) if len(err) else float("nan"),
    }


def no_ratio(cfg: MatchingConfig) -> MatchingConfig:
    """The configuration without the uniqueness test (the paper's matcher)."""
    return dataclasses.replace(cfg, max_ratio=None)


def match_turned(f1: Features, image2: np.ndarray, cfg: MatchingConfig) -> tuple[Matches, np.ndarray]:
    """Match f1 against image2 turned by 180 degrees; returns the matches into the turned
    image's features and the (M, 2) matched points of image 2 in its own frame."""
    turned = cv2.rotate(np.asarray(image2), cv2.ROTATE_180)
    f2 = extract_features(turned, patch_size=f1.patch_size)
    m = match_pair(f1, f2, cfg).matches
    h, w = turned.shape[:2]
    return m, np.array([w - 1.0, h - 1.0]) - f2.points[m.idx2]


def features_from(points: np.ndarray, desc: np.ndarray, shape=(100, 100)) -> Features:
    n = len(points)
    return Features(points, desc.astype(np.float32), np.ones(n, bool), np.ones(n), shape)


# --- Matches ---------------------------------------------------------------------------------
def test_matches_container():
    m = Matches([3, 1, 2], [0, 5, 4], [0.9, 0.95, 0.85])
    assert len(m) == 3 and m.idx1.dtype == np.int64 and m.idx2.dtype == np.int64
    assert m.score.dtype == np.float64
    s = m.subset(np.array([True, False, True]))
    np.testing.assert_array_equal(s.idx1, [3, 2])
    np.testing.assert_array_equal(m.subset([1]).idx2, [5])
    np.testing.assert_array_equal(m.subset(slice(0, 2)).idx1, [3, 1])
    np.testing.assert_array_equal(m.sorted_by_score().idx1, [1, 3, 2])
    kp1 = np.arange(12.0).reshape(6, 2)
    kp2 = -np.arange(12.0).reshape(6, 2)
    x1, x2 = m.points(kp1, kp2)
    np.testing.assert_array_equal(x1, kp1[[3, 1, 2]])
    np.testing.assert_array_equal(x2, kp2[[0, 5, 4]])
    assert len(Matches.empty()) == 0
    with pytest.raises(StereoseedError):
        Matches([1, 2], [1], [0.5, 0.5])


def test_zncc_matrix_is_the_zncc():
    rng = np.random.default_rng(0)
    a = rng.random((4, 25))
    b = rng.random((3, 25))
    def normalise(x: np.ndarray) -> np.ndarray:
        x = x - x.mean(axis=1, keepdims=True)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    da, db = normalise(a), normalise(b)
    expected = np.array([[np.corrcoef(p, q)[0, 1] for q in b] for p in a])
    np.testing.assert_allclose(zncc_matrix(da, db), expected, atol=1e-5)


# --- ZNCC matching on a known warp -----------------------------------------------------------
HOMOGRAPHY = np.array([[0.97, -0.12, 14.0], [0.09, 0.99, -6.0], [1e-4, -5e-5, 1.0]])


@pytest.fixture(scope="module")
def warped_features():
    img1, img2 = warped_pair(HOMOGRAPHY)
    return extract_features(img1), extract_features(img2)


def test_match_zncc_on_a_homography(warped_features):
    f1, f2 = warped_features
    m = match_zncc(f1, f2, MatchingConfig())
    assert len(m) > 100
    x1, x2 = m.points(f1, f2)
    err = np.linalg.norm(apply_h(HOMOGRAPHY, x1) - x2, axis=1)
    assert np.mean(err < 1.5) > 0.95
    assert np.all(m.score > MatchingConfig().min_zncc)
    assert np.all(np.diff(m.score) <= 0), "best first"
    # Mutual: one-to-one.
    assert len(np.unique(m.idx1)) == len(m) == len(np.unique(m.idx2))


def test_match_zncc_search_window(warped_features):
    f1, f2 = warped_features
    m = match_zncc(f1, f2, MatchingConfig(search_radius=0.05), image_width=320)  # 16 px
    x1, x2 = m.points(f1, f2)
    assert len(m) > 20
    assert np.all(np.linalg.norm(x2 - x1, axis=1) <= 16.0 + 1e-6)


def test_uniqueness_rejects_repeated_patterns():
    """Two identical textured tiles: each tile point has an equally good competitor."""
    tile = band_noise((48, 48), seed=4)
    img = np.full((120, 260), 0.5, np.float32)
    img[36:84, 30:78] = tile
    img[36:84, 170:218] = tile
    shifted = np.roll(img, (2, 3), axis=(0, 1))
    f1 = extract_features(img)
    f2 = extract_features(shifted)
    cfg = MatchingConfig(search_radius=1.0)
    loose = match_zncc(f1, f2, no_ratio(cfg))
    strict = match_zncc(f1, f2, cfg)  # default ratio test
    assert len(loose) > 20
    x1, x2 = loose.points(f1, f2)
    wrong = np.linalg.norm(x2 - x1 - [3, 2], axis=1) > 1.0
    assert wrong.any(), "without the ratio test the copies get confused"
    # With it, points of the tiles (all ambiguous) are rejected: almost nothing survives.
    assert len(strict) < 0.1 * len(loose)


def test_match_zncc_degenerate_inputs_log(caplog):
    empty = Features(np.zeros((0, 2)), np.zeros((0, 121), np.float32), np.zeros(0, bool),
                     np.zeros(0), (50, 50))
    rng = np.random.default_rng(0)
    d = rng.standard_normal((5, 121)).astype(np.float32)
    d -= d.mean(1, keepdims=True)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    some = features_from(rng.random((5, 2)) * 50, d, (50, 50))
    cfg = MatchingConfig()
    invalid = Features(some.points, some.desc, np.zeros(5, bool), some.response, (50, 50))
    with warnings.catch_warnings(), caplog.at_level(logging.DEBUG, logger="stereoseed.matching"):
        warnings.simplefilter("error")  # logged, never warned
        assert len(match_zncc(empty, some, cfg)) == 0
        assert len(match_zncc(some, invalid, cfg)) == 0
    assert [r.getMessage() for r in caplog.records] == [
        "no matches: 0 and 5 features", "no matches: no valid descriptor in one of the images"]
    other = features_from(rng.random((5, 2)) * 50, np.zeros((5, 49)), (50, 50))
    with pytest.raises(StereoseedError):
        match_zncc(some, other, cfg)


# --- epipolar geometry -----------------------------------------------------------------------
def two_cameras():
    K = np.array([[700.0, 0, 320], [0, 700, 240], [0, 0, 1]])
    a = np.radians(15)
    R2 = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K @ np.hstack([R2, np.array([[-0.5], [0.05], [0.1]])])
    return P1, P2


def test_band_mask_agrees_with_epipolar_distances():
    P1, P2 = two_cameras()
    F = fundamental_from_projections(P1, P2)
    rng = np.random.default_rng(1)
    x1 = rng.random((60, 2)) * [640, 480]
    x2 = rng.random((70, 2)) * [640, 480]
    mask = epipolar_band_mask(F, x1, x2, 25.0)
    ii, jj = np.meshgrid(np.arange(60), np.arange(70), indexing="ij")
    d = epipolar_distances(F, x1[ii.ravel()], x2[jj.ravel()]).reshape(60, 70)
    clear = np.abs(d - 25.0) > 1e-9  # rounding at the band's edge
    np.testing.assert_array_equal(mask[clear], (d <= 25.0)[clear])
    assert mask.any() and not mask.all()


def test_candidates_and_best_scores_agree_with_numpy():
    from stereoseed.matching.zncc import candidate_mask, candidate_pairs
    from stereoseed.matching._zncc_kernels import best_of_pairs

    P1, P2 = two_cameras()
    F = fundamental_from_projections(P1, P2)
    rng = np.random.default_rng(2)
    x1 = rng.random((80, 2)) * [640, 480]
    x2 = rng.random((90, 2)) * [640, 480]
    near = np.linalg.norm(x1[:, None] - x2[None], axis=2) <= 150.0
    np.testing.assert_array_equal(candidate_mask(x1, x2, 150.0), near)
    banded = candidate_mask(x1, x2, 150.0, F, 25.0)
    ii, jj = np.meshgrid(np.arange(80), np.arange(90), indexing="ij")
    in_band = epipolar_distances(F, x1[ii.ravel()], x2[jj.ravel()]).reshape(80, 90) <= 25.0
    np.testing.assert_array_equal(banded, near & in_band)
    assert banded.any() and (near & ~banded).any()
    indptr, cols = candidate_pairs(x1, x2, 150.0, F, 25.0)
    rows = np.repeat(np.arange(80), np.diff(indptr))
    np.testing.assert_array_equal(np.stack(np.nonzero(banded)), np.stack([rows, cols]))
    # ties and rows without a candidate resolve as np.argmax does
    s = np.where(banded, np.round(rng.random(banded.shape), 1), -np.inf).astype(np.float32)
    best_col, best_score, best_row = best_of_pairs(indptr, cols, s[rows, cols], 90)
    np.testing.assert_array_equal(best_col, np.argmax(s, axis=1))
    np.testing.assert_array_equal(best_row, np.argmax(s, axis=0))
    np.testing.assert_array_equal(best_score, s.max(axis=1))


def test_pair_scores_and_competitors_agree_with_the_score_matrix(textured):
    """The CSR kernels against the dense matrix: the scores of the window's pairs (best over the
    scales), the pairs the bound leaves out all score at most the floor, and the competitors
    are the best scores outside the winner's neighbourhood."""
    from stereoseed.matching.zncc import _bound_terms, _scaled_descriptors, candidate_pairs
    from stereoseed.matching._zncc_kernels import best_competitors, pair_scores

    _, feats = textured
    f1, f2 = feats[0], feats[1]
    v1, v2 = np.flatnonzero(f1.valid), np.flatnonzero(f2.valid)
    x1, x2 = f1.points[v1], f2.points[v2]
    desc1 = np.ascontiguousarray(f1.desc[v1])
    desc2, ok2 = _scaled_descriptors(f2, v2, (1 / 1.2, 1.2))
    dense = np.max(np.where(ok2[:, None, :], np.einsum("id,sjd->sij", desc1.astype(np.float64), desc2), -np.inf), axis=0)
    indptr, cols = candidate_pairs(x1, x2, 150.0)
    rows = np.repeat(np.arange(len(v1)), np.diff(indptr))
    none = np.zeros((len(v1), 0), np.float32), np.zeros(len(v1), np.float32)
    nothing2 = np.zeros(desc2.shape[:2] + (0,), np.float32), np.zeros(desc2.shape[:2], np.float32)
    ptr_all, cols_all, s_all = pair_scores(desc1, desc2, ok2, indptr, cols, *none, *nothing2, -np.inf)
    np.testing.assert_array_equal(ptr_all, indptr)
    np.testing.assert_array_equal(cols_all, cols)
    np.testing.assert_allclose(s_all, dense[rows, cols], atol=2e-6)
    ptr_kept, cols_kept, s_kept = pair_scores(desc1, desc2, ok2, indptr, cols, *_bound_terms(desc1),
                                               *_bound_terms(desc2), 0.6)
    kept_rows = np.repeat(np.arange(len(v1)), np.diff(ptr_kept))
    above = s_all.astype(np.float64) > 0.6  # as the kernel compares: a score of float32(0.6) is above 0.6
    np.testing.assert_array_equal(np.stack([rows[above], cols[above]]), np.stack([kept_rows, cols_kept]))
    np.testing.assert_array_equal(s_kept, s_all[above])
    assert 0 < len(s_kept) < 0.2 * len(s_all)  # the bound's purpose: most pairs are hopeless

    matrix = np.full((len(v1), len(v2)), -np.inf, np.float32)
    matrix[rows, cols] = s_all
    which = np.flatnonzero(np.isfinite(matrix).any(axis=1))[:50]
    winners = np.argmax(matrix[which], axis=1)
    comp1, comp2 = best_competitors(indptr, cols, s_all, which, winners, x1, x2, 5.5**2)
    far2 = np.linalg.norm(x2[None, :] - x2[winners][:, None], axis=2) > 5.5
    far1 = np.linalg.norm(x1[None, :] - x1[which][:, None], axis=2) > 5.5
    np.testing.assert_array_equal(comp2, np.where(far2, matrix[which], -np.inf).max(axis=1))
    np.testing.assert_array_equal(comp1, np.where(far1, matrix[:, winners].T, -np.inf).max(axis=1))


def test_filter_epipolar_keeps_the_band():
    P1, P2 = two_cameras()
    F = fundamental_from_projections(P1, P2)
    rng = np.random.default_rng(2)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], (50, 3))
    x1, x2 = project(P1, X), project(P2, X)
    x2[:20] += rng.normal(0, 5, (20, 2))
    m = Matches(np.arange(50), np.arange(50), np.ones(50))
    kept = filter_epipolar(m, x1, x2, F, 1.0)
    d = epipolar_distances(F, x1, x2)
    np.testing.assert_array_equal(np.sort(kept.idx1), np.flatnonzero(d <= 1.0))
    assert set(range(20, 50)) <= set(kept.idx1.tolist())


def test_filter_fundamental_ransac_recovers_geometry_deterministically():
    P1, P2 = two_cameras()
    F_true = fundamental_from_projections(P1, P2)
    rng = np.random.default_rng(3)
    X = rng.uniform([-1.5, -1, 4], [1.5, 1, 7], (150, 3))
    x1 = project(P1, X) + rng.normal(0, 0.2, (150, 2))
    x2 = project(P2, X) + rng.normal(0, 0.2, (150, 2))
    x2[:45] = rng.random((45, 2)) * [640, 480]  # 30 % gross outliers
    m = Matches(np.arange(150), np.arange(150), np.linspace(1, 0.8, 150))
    cfg = MatchingConfig()
    inl, F, _ = filter_fundamental_ransac(m, x1, x2, cfg)
    assert F is not None and F.shape == (3, 3)
    assert np.isclose(np.linalg.norm(F), 1.0)
    truly = epipolar_distances(F_true, x1, x2) < 1.5
    assert np.mean(truly[inl.idx1]) > 0.97
    assert len(inl) >= 0.9 * truly[45:].sum()
    inl2, F2, _ = filter_fundamental_ransac(m, x1, x2, cfg)
    np.testing.assert_array_equal(inl.idx1, inl2.idx1)
    np.testing.assert_array_equal(F, F2)
    inl3, F3, _ = filter_fundamental_ransac(m, x1, x2, cfg, method=cv2.FM_RANSAC)
    assert F3 is not None and np.mean(truly[inl3.idx1]) > 0.97


def test_filter_fundamental_ransac_keeps_the_best_supported_run():
    """Several robust runs, the F with the most inliers kept: never fewer inliers than the first
    run alone, whatever the seed."""
    P1, P2 = two_cameras()
    rng = np.random.default_rng(5)
    X = rng.uniform([-1.5, -1, 4], [1.5, 1, 7], (120, 3))
    x1 = project(P1, X) + rng.normal(0, 0.3, (120, 2))
    x2 = project(P2, X) + rng.normal(0, 0.3, (120, 2))
    x2[:70] = rng.random((70, 2)) * [640, 480]  # a weak pair: 58 % gross outliers
    m = Matches(np.arange(120), np.arange(120), np.linspace(1, 0.8, 120))
    for seed in range(4):
        one, _, _ = filter_fundamental_ransac(m, x1, x2, MatchingConfig(seed=seed, ransac_runs=1))
        best, F, _ = filter_fundamental_ransac(m, x1, x2, MatchingConfig(seed=seed, ransac_runs=3))
        assert len(best) >= len(one)
        assert np.mean(best.idx1 >= 70) > 0.9


def test_filter_fundamental_ransac_says_why_there_is_no_f():
    m = Matches(np.arange(5), np.arange(5), np.ones(5))
    pts = np.random.default_rng(0).random((5, 2)) * 100
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, F, reason = filter_fundamental_ransac(m, pts, pts, MatchingConfig())
    assert len(out) == 0 and F is None
    assert "at least 8" in reason


# --- localisation check ----------------------------------------------------------------------
def test_align_matches_recovers_an_affine_warp_to_hundredths_of_a_pixel(warped_features):
    f1, f2 = warped_features
    m = match_zncc(f1, f2, MatchingConfig())
    al = align_matches(f1, f2, m, MatchingConfig())
    x1, _ = m.points(f1, f2)
    truth = apply_h(HOMOGRAPHY, x1)
    ok = al.converged
    assert ok.mean() > 0.95
    err = np.linalg.norm(al.x2[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.03
    assert np.percentile(err, 90) < 0.1
    assert np.all(al.zncc[ok] > 0.9)
    # The local linear map is the homography's Jacobian.
    J = np.array([[0.97, -0.12], [0.09, 0.99]])
    assert np.median(np.abs(al.affine[ok] - J).max(axis=(1, 2))) < 0.1
    # filter_localization keeps the well-localised ones and scores them by aligned ZNCC.
    kept = filter_localization(m, f1, f2, MatchingConfig())
    assert 0.5 * len(m) < len(kept) <= len(m)
    assert np.all(kept.score > 0.9)


def test_align_matches_needs_grey_images(warped_features, caplog):
    f1, f2 = warped_features
    bare = Features(f1.points, f1.desc, f1.valid, f1.response, f1.image_shape)
    with pytest.raises(StereoseedError):
        align_matches(bare, f2, Matches([0], [0], [1.0]), MatchingConfig())
    with caplog.at_level(logging.INFO, logger="stereoseed.matching"):
        pair = match_pair(bare, f2, MatchingConfig(), F=np.eye(3))
    assert "localisation check skipped" in caplog.text
    assert pair.stats["localization"].startswith("skipped")


# --- the synthetic box: quality targets ------------------------------------------------------
@pytest.fixture(scope="module", params=[0.0, 2.0], ids=["sigma0", "sigma2"])
def textured(request, box_scene, box_scene_noisy):
    scene = {0.0: box_scene, 2.0: box_scene_noisy}[request.param].prefix(3)
    return scene, [extract_features(im) for im in scene.images]


@pytest.fixture(scope="module")
def plain(plain_box_scene):
    scene = plain_box_scene.prefix(3)
    return scene, [extract_features(im) for im in scene.images]


@pytest.mark.parametrize("pair,known_F", [((0, 1), True), ((0, 1), False), ((1, 2), False)])
def test_quality_on_the_textured_box(textured, pair, known_F):
    """>= 300 kept, >= 95 % within 1 px and >= 99 % within 3 px of the exact correspondence."""
    scene, feats = textured
    i, j = pair
    F = fundamental_from_projections(scene.P[i], scene.P[j]) if known_F else None
    m = match_pair(feats[i], feats[j], MatchingConfig(), F=F).matches
    acc = accuracy(scene, i, j, feats[i], feats[j], m)
    print(f"textured sigma={scene.config.noise_sigma} pair {pair} known F={known_F}: {acc}")
    assert acc["kept"] >= 300
    assert acc["evaluated"] >= 0.9 * acc["kept"]
    assert acc["within_1px"] >= 0.95
    assert acc["within_3px"] >= 0.99


def test_refine_features_moves_matched_points_onto_the_truth(textured):
    """Refined positions of image 2 are ~10x closer to the exact correspondence."""
    scene, feats = textured
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    m = match_pair(feats[0], feats[1], MatchingConfig(), F=F).matches
    refined = refine_features(feats[0], feats[1], m, MatchingConfig())
    before = accuracy(scene, 0, 1, feats[0], feats[1], m)
    after = accuracy(scene, 0, 1, feats[0], refined, m)
    print(f"detected {before}\nrefined  {after}")
    assert after["median_px"] < 0.1 < before["median_px"]
    assert after["within_1px"] >= 0.99
    # Same indices; unmatched points untouched; descriptors follow the points.
    unmatched = np.setdiff1d(np.arange(len(feats[1])), m.idx2)
    np.testing.assert_array_equal(refined.points[unmatched], feats[1].points[unmatched])
    desc, _ = describe(feats[1].gray, refined.points[m.idx2[:5]], feats[1].patch_size)
    np.testing.assert_allclose(refined.desc[m.idx2[:5]], desc, atol=1e-6)
    assert feats[1].points is not refined.points


def test_a_pair_cache_changes_nothing_but_the_work(textured):
    """Robust F, then known F, then refinement through one PairCache: the same matches and
    positions as without it, and the second round aligns (almost) nothing new."""
    scene, feats = textured
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    cache = PairCache(feats[0], feats[1])
    for known in (None, F):
        plain = match_pair(feats[0], feats[1], MatchingConfig(), F=known).matches
        cached = match_pair(feats[0], feats[1], MatchingConfig(), F=known, cache=cache).matches
        np.testing.assert_array_equal(plain.idx1, cached.idx1)
        np.testing.assert_array_equal(plain.idx2, cached.idx2)
        np.testing.assert_allclose(plain.score, cached.score, atol=1e-5)
    aligned = len(cache.codes)
    refined = refine_features(feats[0], feats[1], cached, MatchingConfig(), cache=cache)
    assert len(cache.codes) == aligned  # every kept match was aligned while matching
    np.testing.assert_array_equal(refined.points, refine_features(feats[0], feats[1], cached, MatchingConfig()).points)
    assert not PairCache(feats[1], feats[0]).covers(feats[0], feats[1])


def test_guided_matching_beats_the_papers_recipe(textured):
    """The paper's recipe (11x11 ZNCC > 0.8, mutual, 2 px band afterwards) on the same pair."""
    scene, feats = textured
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    cfg = MatchingConfig()
    plain_zncc = match_zncc(feats[0], feats[1], no_ratio(cfg))
    paper = filter_epipolar(plain_zncc, feats[0], feats[1], F, 2.0)
    ours = match_pair(feats[0], feats[1], cfg, F=F).matches
    acc_paper = accuracy(scene, 0, 1, feats[0], feats[1], paper)
    acc_ours = accuracy(scene, 0, 1, feats[0], feats[1], ours)
    print(f"paper recipe {acc_paper}\nmatch_pair   {acc_ours}")
    assert acc_ours["kept"] > 3 * acc_paper["kept"]
    assert acc_ours["within_1px"] >= acc_paper["within_1px"]


def test_plain_box_the_repeated_squares(plain):
    """The paper's plain box: only the squares' corners; identical squares are the trap.

    With the calibrated pair's F the squares are matched along their epipolar band; the few
    wrong matches are whole-square confusions (> 3 px), not localisation errors. Without F the
    repeated pattern cannot give a trustworthy F: the robust path must return nothing rather
    than a wrong geometry.
    """
    scene, feats = plain
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    m = match_pair(feats[0], feats[1], MatchingConfig(), F=F).matches
    acc = accuracy(scene, 0, 1, feats[0], feats[1], m)
    print(f"plain box pair (0, 1), known F: {acc}")
    assert acc["kept"] >= 60
    assert acc["within_1px"] >= 0.9
    pair = match_pair(feats[1], feats[2], MatchingConfig())
    m2, F2 = pair.matches, pair.F
    assert (F2 is None) == (len(m2) == 0) == pair.stats["geometry"].startswith("robust F failed")
    acc2 = accuracy(scene, 1, 2, feats[1], feats[2], m2)
    print(f"plain box pair (1, 2), robust F: {acc2}")
    assert len(m2) == 0 or acc2["within_1px"] >= 0.9


# --- drawing ----------------------------------------------------------------------------------
def test_draw_matches_writes_a_side_by_side_png(tmp_path: Path, warped_features):
    f1, f2 = warped_features
    m = match_zncc(f1, f2, MatchingConfig())
    out = tmp_path / "sub" / "matches.png"
    canvas = draw_matches(f1.gray, f1, (f2.gray * 255).astype(np.uint8), f2, m, out, max_lines=50)
    assert canvas.shape == (240, 640, 3) and canvas.dtype == np.uint8
    back = cv2.imread(str(out))
    assert back is not None and back.shape == (240, 640, 3)
    np.testing.assert_array_equal(back, canvas)


# --- real data: Middlebury templeSparseRing --------------------------------------------------
def read_middlebury(folder: Path) -> tuple[list[str], dict[str, np.ndarray]]:
    """Ring order and P = K [R | t] of every image (templeSR_par.txt format)."""
    order = (folder / "ring_order.txt").read_text().split()
    par = next(folder.glob("*_par.txt"))
    cams = {}
    for line in par.read_text().splitlines()[1:]:
        parts = line.split()
        if len(parts) != 22:
            continue
        v = np.array(parts[1:], float)
        cams[parts[0]] = v[:9].reshape(3, 3) @ np.hstack([v[9:18].reshape(3, 3), v[18:21, None]])
    return order, cams


def test_temple_ring_epipolar_accuracy(temple_dir):
    """Every consecutive pair of the ring, robust path (F unknown to the matcher).

    Kept matches must lie < 0.5 px (median) from their epipolar lines under the ground-truth
    cameras. Views with opposite gantry latitude are rotated 180 degrees in the image plane
    (README of the data); ZNCC is not rotation invariant, so those pairs must not come back with
    a wrong geometry, and must match once the second image is turned back.
    """
    order, cams = read_middlebury(temple_dir)
    images = {name: cv2.imread(str(temple_dir / name)) for name in order}
    feats = {name: extract_features(images[name]) for name in order}
    report = []
    for a, b in zip(order[:-1], order[1:]):
        F_true = fundamental_from_projections(cams[a], cams[b])
        R_a, R_b = decompose_projection(cams[a])[1], decompose_projection(cams[b])[1]
        upright = float(R_a[1] @ R_b[1]) > 0  # image "down" axes agree
        m = match_pair(feats[a], feats[b], MatchingConfig()).matches
        if upright:
            x1, x2 = m.points(feats[a], feats[b])
        else:  # the plain match must not invent a geometry; turned back, it must match
            assert len(m) < 15, (a, b, len(m))
            m, x2 = match_turned(feats[a], images[b], MatchingConfig())
            x1 = feats[a].points[m.idx1]
        med = float(np.median(epipolar_distances(F_true, x1, x2))) if len(m) else float("nan")
        report.append((a, b, upright, len(m), med))
        assert len(m) >= 20, (a, b, upright, len(m))
        # measured 0.10-0.24 px upright; 0.50-0.71 px on the three turned pairs, whose matches
        # spread over the whole 1 px RANSAC band (unexplained yet: see the closing note of issue 3)
        assert med < (0.5 if upright else 0.75), (a, b, med)
    for a, b, u, n, d in report:
        print(f"{a} -> {b} upright={u} kept={n} median_epipolar_px={d:.3f}")


# --- robustness ------------------------------------------------------------------------------
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n1=st.integers(0, 40),
    n2=st.integers(0, 40),
    seed=st.integers(0, 2**16),
    known_F=st.booleans(),
    mutual=st.booleans(),
)
def test_matching_never_crashes_on_random_points(n1, n2, seed, known_F, mutual):
    rng = np.random.default_rng(seed)
    gray = rng.random((60, 80)).astype(np.float32)
    if seed % 3 == 0:
        gray[:] = 0.5  # constant image: every descriptor invalid
    p1 = rng.uniform(-5, 85, (n1, 2))
    p2 = rng.uniform(-5, 85, (n2, 2))
    d1, v1 = describe(gray, p1, 11)
    d2, v2 = describe(gray, p2, 11)
    f1 = Features(p1, d1, v1, np.ones(n1), (60, 80), gray)
    f2 = Features(p2, d2, v2, np.ones(n2), (60, 80), gray)
    cfg = MatchingConfig(mutual=mutual, min_zncc=-1.0, candidate_min_zncc=-1.0)
    F = rng.standard_normal((3, 3)) if known_F else None
    pair = match_pair(f1, f2, cfg, F=F)
    assert isinstance(pair, PairMatches)
    m = pair.matches
    z = match_zncc(f1, f2, no_ratio(cfg))
    for mm in (m, z):
        assert np.all((mm.idx1 >= 0) & (mm.idx1 < n1)) and np.all((mm.idx2 >= 0) & (mm.idx2 < n2))
        assert np.all(v1[mm.idx1]) and np.all(v2[mm.idx2])


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    image=hnp.arrays(
        np.uint8, st.tuples(st.integers(0, 64), st.integers(0, 64)), elements=st.integers(0, 255)
    ),
    constant=st.booleans(),
)
def test_pipeline_never_crashes_on_random_images(image, constant):
    if constant:
        image = np.full_like(image, 77)
    f1 = extract_features(image, FeatureConfig(border=4))
    f2 = extract_features(np.ascontiguousarray(image[::-1]), FeatureConfig(border=4))
    pair = match_pair(f1, f2, MatchingConfig())
    m, F = pair.matches, pair.F
    assert len(m) <= min(len(f1), len(f2))
    assert F is None or F.shape == (3, 3)


# --- the configuration and the pair recipe's API ------------------------------------------------
@pytest.mark.parametrize("field,value", [
    ("patch_size", 10), ("patch_size", 0), ("patch_size", -3), ("align_patch_size", 14),
    ("min_zncc", 1.5), ("candidate_min_zncc", -1.2), ("min_aligned_zncc", 2.0),
    ("relaxed_min_aligned_zncc", -3.0), ("max_ratio", 0.0), ("guided_max_ratio", 1.5),
    ("first_pass_ratio", -0.1), ("search_radius", 0.0), ("epipolar_band_px", -1.0),
    ("ransac_threshold_px", 0.0), ("ransac_confidence", 1.0), ("ransac_runs", 0),
    ("ransac_max_iters", 0), ("min_f_inliers", -1), ("max_shift_px", 0.0),
    ("relaxed_max_shift_px", -0.5), ("scales", (1.2, 0.0)), ("align_max_iters", 0), ("align_tol_px", 0.0),
])
def test_a_bad_matching_config_raises_a_one_line_value_error(field, value):
    with pytest.raises(ValueError, match=field) as info:
        MatchingConfig(**{field: value})
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=field):  # replace() validates too
        dataclasses.replace(MatchingConfig(), **{field: value})


def test_the_matching_config_stays_frozen_and_plain_data():
    cfg = MatchingConfig(scales=[0.9, 1.1], max_ratio=None)
    assert cfg.scales == (0.9, 1.1) and hash(cfg) == hash(MatchingConfig(scales=(0.9, 1.1), max_ratio=None))
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.min_zncc = 0.5  # type: ignore[misc]
    d = dataclasses.asdict(cfg)
    assert d["scales"] == (0.9, 1.1) and MatchingConfig(**d) == cfg
    # the paper's threshold for plain ZNCC matching, the looser one for the recipe's candidates
    assert MatchingConfig().min_zncc == 0.8 and MatchingConfig().candidate_min_zncc == 0.6


def test_relaxed_changes_only_the_localisation_thresholds():
    cfg = MatchingConfig(max_shift_px=0.5, min_aligned_zncc=0.95, relaxed_max_shift_px=2.0,
                         relaxed_min_aligned_zncc=0.7, seed=4)
    relaxed = cfg.relaxed()
    before, after = dataclasses.asdict(cfg), dataclasses.asdict(relaxed)
    changed = {k for k in before if before[k] != after[k]}
    assert changed == {"max_shift_px", "min_aligned_zncc"}
    assert relaxed.max_shift_px == 2.0 and relaxed.min_aligned_zncc == 0.7
    assert cfg.max_shift_px == 0.5 and cfg.min_aligned_zncc == 0.95  # a copy


def test_match_pair_always_returns_pair_matches(textured):
    scene, feats = textured
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    known = match_pair(feats[0], feats[1], MatchingConfig(), F=F)
    assert isinstance(known, PairMatches) and isinstance(known.matches, Matches)
    np.testing.assert_array_equal(known.F, F)
    assert known.stats["geometry"] == "known F" and known.stats["kept"] == len(known.matches) > 0
    robust = match_pair(feats[0], feats[1], MatchingConfig())
    assert isinstance(robust, PairMatches) and len(robust.matches) > 0
    assert robust.F.shape == (3, 3) and np.isclose(np.linalg.norm(robust.F), 1.0)
    assert robust.stats["geometry"] == "robust F"
    assert robust.stats["kept"] == len(robust.matches) >= robust.stats["ransac_inliers"] >= 15
    with pytest.raises(dataclasses.FrozenInstanceError):
        robust.F = None  # type: ignore[misc]


def test_match_pair_without_a_robust_f_is_empty_and_says_why(caplog):
    """Two unrelated textures: no F, no matches, the reason in the stats and in the log (not a
    warning: a pair without F is normal and the pipeline reports it)."""
    f1 = extract_features(warped_pair(np.eye(3), seed=0)[0])
    f2 = extract_features(warped_pair(np.eye(3), seed=1)[0])
    with warnings.catch_warnings(), caplog.at_level(logging.DEBUG, logger="stereoseed.matching"):
        warnings.simplefilter("error")
        pair = match_pair(f1, f2, MatchingConfig())
    assert isinstance(pair, PairMatches)
    assert len(pair.matches) == 0 and pair.F is None and pair.stats["kept"] == 0
    assert pair.stats["candidates"] > 0
    assert pair.stats["geometry"].startswith("robust F failed: ")
    assert "at least 8 matches" in pair.stats["geometry"]
    assert "at least 8 matches" in caplog.text


def test_the_relaxed_match_reuses_the_pair_cache(textured, monkeypatch):
    """The pipeline matches a weak pair again with config.relaxed(): the alignment parameters
    are the same, so the alignments made by the first match come from the cache (with a known F
    the candidates are the same: nothing is aligned again), and the results are those of an
    uncached relaxed match."""
    scene, feats = textured
    cfg = MatchingConfig()
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    kernel = alignment.align_kernel
    aligned: list[int] = []
    monkeypatch.setattr(alignment, "align_kernel", lambda *a: aligned.append(len(a[4])) or kernel(*a))

    def relaxed_rows(known, cache):
        match_pair(feats[0], feats[1], cfg, F=known, cache=cache)
        aligned.clear()
        m = match_pair(feats[0], feats[1], cfg.relaxed(), F=known, cache=cache).matches
        return m, sum(aligned)

    for known in (F, None):
        cache = PairCache(feats[0], feats[1])
        cached, rows_cached = relaxed_rows(known, cache)
        alone, rows_alone = relaxed_rows(known, None)
        np.testing.assert_array_equal(cached.idx1, alone.idx1)
        np.testing.assert_array_equal(cached.idx2, alone.idx2)
        assert sum(k[0] == "pairs" for k in cache.zncc) == (known is None) and rows_alone > 100
        if known is not None:
            assert rows_cached == 0
        else:  # a new robust F guides a few new candidates
            assert rows_cached < 0.25 * rows_alone


def test_gradient_cache_lets_a_freed_image_go():
    import gc

    from stereoseed.matching import alignment

    gray = np.random.default_rng(0).random((60, 80)).astype(np.float32)
    g, gx, _ = alignment._with_gradients(gray)
    assert g is gray and alignment._with_gradients(gray)[1] is gx  # the cached gradients
    key = id(gray)
    del gray, g
    gc.collect()
    assert key not in alignment._GRADIENTS


def test_gradient_cache_holds_a_bounded_number_of_bytes(monkeypatch):
    """Large images' gradients are kept within the byte limit (the newest always), and a finished
    run lets them all go."""
    from stereoseed.matching import alignment

    monkeypatch.setattr(alignment, "_GRADIENT_BYTES", 3 * 2 * 4 * 60 * 80)  # three images' gx and gy
    grays = [np.random.default_rng(i).random((60, 80)).astype(np.float32) for i in range(6)]
    for g in grays:
        alignment._with_gradients(g)
    kept = [k for k in alignment._GRADIENTS if k in {id(g) for g in grays}]
    assert kept == [id(g) for g in grays[-3:]]
    alignment.release_gradients()
    assert not alignment._GRADIENTS
