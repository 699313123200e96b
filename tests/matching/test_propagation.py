"""Tests of stereoseed.matching.propagation.core (Lhuillier & Quan match propagation + sub-pixel refinement).

Three groups:
* a synthetic texture pair related by a known affine map (exact dense ground truth);
* a small pure-Python reference implementation of the algorithm of paper.md, compared match
  for match with the Numba kernel on tiny random pairs;
* the rendered box scene of stereoseed.synthetic.scene (skipped if that module is missing), where the
  ground truth comes from ray casting: coverage and accuracy on the ground and the box faces.
"""
from __future__ import annotations

import heapq

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stereoseed.geometry.projection import skew
from stereoseed.config import PropagationConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.image import to_gray
from stereoseed.matching.propagation.core import PropagationResult, propagate, texture_mask, warm_up
from stereoseed.output.visualize import disparity_image, save_propagation_png


def as_grey01(image: np.ndarray) -> np.ndarray:
    """The propagation's own conversion: float64 grey in [0, 1]."""
    return to_gray(image, np.float64)


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def multiscale_texture(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w) float64 in [0, 1]: sum of upsampled noise octaves (blobs of 2 to 16 px)."""
    img = np.zeros((h, w))
    for s in (2, 4, 8, 16):
        n = rng.random((h // s + 3, w // s + 3))
        n = cv2.resize(n, ((w // s + 3) * s, (h // s + 3) * s), interpolation=cv2.INTER_CUBIC)
        img += n[s:s + h, s:s + w] / np.sqrt(s)
    return (img - img.min()) / (img.max() - img.min())


def integer_x2(result: PropagationResult) -> np.ndarray:
    """(M, 2) int integer positions in image 2 of the matches."""
    return result.integer_matches[:, 2:4]


def line_distances(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of each x2 (N, 2) to the epipolar line F x1 in image 2."""
    l2 = np.column_stack([x1, np.ones(len(x1))]) @ F.T
    num = np.abs(np.sum(np.column_stack([x2, np.ones(len(x2))]) * l2, axis=1))
    return num / np.hypot(l2[:, 0], l2[:, 1])


@pytest.fixture(scope="module", autouse=True)
def _jit():
    warm_up()  # compile once (or load the Numba cache) so that no test pays for it


# --------------------------------------------------------------------------------------------
# Synthetic texture pair with a known affine correspondence
# --------------------------------------------------------------------------------------------

H, W = 240, 320
FLAT = (slice(150, 210), slice(30, 110))  # an untextured rectangle in image 1


@pytest.fixture(scope="module")
def affine_pair():
    """img1, img2 (H, W) float64; A (2, 3) with x2 = A @ (x1, 1); F consistent with A; seeds."""
    rng = np.random.default_rng(7)
    img1 = multiscale_texture(H, W, rng)
    img1[FLAT] = 0.5
    ang, sc = np.deg2rad(3.0), 1.04
    A = np.array([[sc * np.cos(ang), -sc * np.sin(ang), 5.3],
                  [sc * np.sin(ang), sc * np.cos(ang), -3.6]])
    # warpAffine maps dst(x2) = src(inverse(A) x2) with WARP_INVERSE_MAP unset: img2(A x1) = img1(x1)
    img2 = cv2.warpAffine(img1, A, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    img2 = np.clip(img2 + rng.normal(0.0, 0.005, img2.shape), 0.0, 1.0)
    # For a planar scene any F = [e2]_x Hom is consistent with the homography; e2 at infinity
    # gives nearly horizontal epipolar lines.
    Hom = np.vstack([A, [0.0, 0.0, 1.0]])
    F = skew(np.array([1.0, 0.15, 0.0])) @ Hom
    F /= np.linalg.norm(F)
    x1 = np.column_stack([rng.uniform(20, 140, 40), rng.uniform(20, 130, 40)])
    seeds = np.hstack([x1, x1 @ A[:, :2].T + A[:, 2]])
    return img1, img2, A, F, seeds


def gt_x2(A: np.ndarray, x1: np.ndarray) -> np.ndarray:
    return x1 @ A[:, :2].T + A[:, 2]


def coverage_target(img1: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(H, W) bool: textured pixels of image 1 with a full window whose true match has a full
    window inside image 2."""
    tex = texture_mask(img1, PropagationConfig().min_texture)
    yy, xx = np.mgrid[0:H, 0:W]
    g = gt_x2(A, np.column_stack([xx.ravel(), yy.ravel()]).astype(float)).reshape(H, W, 2)
    m = 3
    inside = (g[..., 0] >= m) & (g[..., 0] <= W - 1 - m) & (g[..., 1] >= m) & (g[..., 1] <= H - 1 - m)
    border = np.zeros((H, W), bool)
    border[2:-2, 2:-2] = True
    return tex & inside & border


@pytest.mark.parametrize("use_f", [False, True])
def test_affine_pair_coverage_and_accuracy(affine_pair, use_f):
    img1, img2, A, F, seeds = affine_pair
    res = propagate(img1, img2, seeds, F if use_f else None, subpixel=False)
    target = coverage_target(img1, A)
    m = res.matches
    x1i = m[:, :2].astype(int)
    matched = np.zeros((H, W), bool)
    matched[x1i[:, 1], x1i[:, 0]] = True
    coverage = (matched & target).sum() / target.sum()
    assert coverage > 0.80, coverage
    # without refinement the error is rounding only: median ~0.38 px for uniform offsets
    err = np.linalg.norm(m[:, 2:] - gt_x2(A, m[:, :2]), axis=1)
    assert np.median(err) < 0.6
    assert np.mean(err < 1.0) > 0.9
    assert np.all(m[:, 2:] == np.round(m[:, 2:]))  # integer positions when subpixel is off
    # the flat rectangle is untextured: nothing matched there
    assert not matched[FLAT][2:-2, 2:-2].any()
    assert res.n_seeds_used >= 20  # exact seeds, but rounding both ends can cost ZNCC


@pytest.mark.parametrize("method", ["quadratic", "affine"])
@pytest.mark.parametrize("use_f", [False, True])
def test_affine_pair_subpixel(affine_pair, method, use_f):
    img1, img2, A, F, seeds = affine_pair
    Fu = F if use_f else None
    base = propagate(img1, img2, seeds, Fu, subpixel=False)
    res = propagate(img1, img2, seeds, Fu, subpixel=True, subpixel_method=method)
    # refinement never changes which pixels are matched
    np.testing.assert_array_equal(res.match_x, base.match_x)
    np.testing.assert_array_equal(res.matches[:, :2], base.matches[:, :2])
    err0 = np.linalg.norm(base.matches[:, 2:] - gt_x2(A, base.matches[:, :2]), axis=1)
    err = np.linalg.norm(res.matches[:, 2:] - gt_x2(A, res.matches[:, :2]), axis=1)
    assert np.median(err) <= 0.5
    assert np.median(err) < 0.6 * np.median(err0)  # rounding error is ~0.38 px median
    assert np.mean(err < 1.0) > 0.95
    assert res.subpixel and res.subpixel_method == method
    assert set(np.unique(res.refined_by)) <= ({1} if method == "quadratic" else {1, 2})
    if method == "quadratic" and not use_f:
        # offsets of the 3x3 fit are clamped to +-1 px per axis
        assert np.all(np.abs(res.matches[:, 2:] - base.matches[:, 2:]) <= 1.0 + 1e-12)
    if use_f:
        # every refined x2 lies on the epipolar line of its x1
        d = line_distances(F, res.matches[:, :2], res.matches[:, 2:])
        assert d.max() < 1e-6


@pytest.mark.parametrize("method", ["quadratic", "affine"])
@pytest.mark.parametrize("use_f", [False, True])
def test_refine_rows_gives_those_rows_exactly(affine_pair, method, use_f):
    """Refining a few chosen rows gives them bit for bit as the full refinement does (the
    affine passes fit on neighbours refined before); every other row keeps its whole pixel."""
    img1, img2, A, F, seeds = affine_pair
    Fu = F if use_f else None
    full = propagate(img1, img2, seeds, Fu, subpixel=True, subpixel_method=method)
    asked = {}

    def every_37th(whole, scores):
        assert np.all(whole == np.round(whole)) and scores.dtype == np.float32 and len(scores) == len(whole)
        asked["n"] = len(whole)
        return np.arange(3, len(whole), 37)

    part = propagate(img1, img2, seeds, Fu, subpixel=True, subpixel_method=method, refine_rows=every_37th)
    rows = np.arange(3, full.n_matches, 37)
    assert asked["n"] == full.n_matches and len(rows) > 100
    np.testing.assert_array_equal(part.matches[rows], full.matches[rows])
    np.testing.assert_array_equal(part.refined_by[rows], full.refined_by[rows])
    rest = np.setdiff1d(np.arange(full.n_matches), rows)
    np.testing.assert_array_equal(part.matches[rest], full.integer_matches[rest].astype(np.float64))
    assert np.all(part.refined_by[rest] == 0)
    assert np.any(full.matches[rows, 2:] != np.round(full.matches[rows, 2:]))  # something was refined


def test_one_match_per_pixel_in_each_image(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    res = propagate(img1, img2, seeds, F)
    im = res.integer_matches
    assert len(np.unique(im[:, 0] + W * im[:, 1])) == res.n_matches
    assert len(np.unique(im[:, 2] + W * im[:, 3])) == res.n_matches
    # the maps agree with the list and are -1 elsewhere
    assert (res.match_x >= 0).sum() == res.n_matches
    assert ((res.match_x >= 0) == (res.match_y >= 0)).all()
    assert res.match_x.dtype == np.int32 and res.match_x.shape == (H, W)


def test_result_types_and_scores(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    res = propagate(img1.astype(np.float32), img2.astype(np.float32), seeds, F)
    assert res.matches.dtype == np.float64 and res.matches.shape == (res.n_matches, 4)
    assert res.scores.dtype == np.float32 and res.scores.shape == (res.n_matches,)
    assert np.all(res.scores > 0.5) and np.all(res.scores <= 1.0 + 1e-6)
    assert res.n_seeds_given == len(seeds)
    # seeds come first and are the rounded seed positions
    used = res.integer_matches[: res.n_seeds_used]
    rounded = {tuple(r) for r in np.rint(seeds).astype(int)}
    assert all(tuple(r) in rounded for r in used)
    for key in ("prepare", "propagate", "subpixel", "total"):
        assert res.timings[key] >= 0.0
    rep = res.report()
    assert rep["n_matches"] == res.n_matches and sum(rep["refined_by"].values()) == res.n_matches


def test_epipolar_band_respected(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    cfg = PropagationConfig(epipolar_band_px=1.0)
    res = propagate(img1, img2, seeds, F, cfg, subpixel=False)
    grown = res.integer_matches[res.n_seeds_used:]  # seeds are not band-tested
    d = line_distances(F, grown[:, :2].astype(float), grown[:, 2:].astype(float))
    assert d.max() <= 1.0 + 1e-9
    # a narrower band keeps fewer matches
    narrow = propagate(img1, img2, seeds, F, PropagationConfig(epipolar_band_px=0.3), subpixel=False)
    grown = narrow.integer_matches[narrow.n_seeds_used:].astype(float)
    d = line_distances(F, grown[:, :2], grown[:, 2:])
    assert d.max() <= 0.3 + 1e-9 and narrow.n_matches < res.n_matches
    # a wrong F (horizontal lines y2 = y1, while the true motion has a vertical component)
    # forces every grown match onto its lines, whatever the images say
    F_wrong = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    wrong = propagate(img1, img2, seeds, F_wrong, subpixel=False)
    grown = wrong.integer_matches[wrong.n_seeds_used:]
    assert np.abs(grown[:, 3] - grown[:, 1]).max() <= 1
    assert wrong.n_matches < res.n_matches


def test_empty_seeds_give_empty_result(affine_pair):
    img1, img2, A, F, _ = affine_pair
    for seeds in (np.zeros((0, 4)), [], np.empty(0)):
        res = propagate(img1, img2, seeds, F)
        assert res.n_matches == 0 and res.matches.shape == (0, 4) and res.scores.shape == (0,)
        assert res.n_seeds_used == 0 and (res.match_x == -1).all() and (res.match_y == -1).all()
        assert disparity_image(res, img1.shape).max() == 0


def test_flat_image_gives_empty_result():
    flat = np.full((60, 80), 0.4, dtype=np.float32)
    seeds = np.array([[40.0, 30.0, 41.0, 30.0], [20.0, 20.0, 20.0, 20.0]])
    for F in (None, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])):
        res = propagate(flat, flat, seeds, F)
        assert res.n_matches == 0 and res.n_seeds_used == 0


def test_bad_seeds_are_dropped_not_fatal(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    good = seeds[:3]
    bad = np.array([
        [-5.0, 10.0, 0.0, 10.0],  # outside image 1
        [10.0, 10.0, W + 3.0, 10.0],  # outside image 2
        [1.0, 1.0, 1.0, 1.0],  # window leaves the image
        [np.nan, 5.0, 5.0, 5.0],
        [60.0, 170.0, 65.0, 168.0],  # inside the flat rectangle
    ])
    good = np.rint(good)
    dup = good[:1] + np.array([[0.0, 0.0, 0.2, -0.2]])  # same rounded pixels as the first seed
    res = propagate(img1, img2, np.vstack([good, bad, dup]), F, subpixel=False)
    assert res.n_seeds_given == 9 and res.n_seeds_used == 3
    assert res.n_matches > 1000
    # seeds whose ZNCC is below the threshold are dropped: an inverted image 2 gives ZNCC = -1
    inverted = propagate(img1, 1.0 - img1, np.column_stack([good[:, :2], good[:, :2]]), None)
    assert inverted.n_seeds_used == 0 and inverted.n_matches == 0


def test_seed_scores_decide_conflicts(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    s = seeds[0]
    # two seeds share pixel x1; the second is off by 1 px in image 2
    pair = np.array([s, s + np.array([0.0, 0.0, 1.0, 0.0])])
    first = propagate(img1, img2, pair, None, subpixel=False)
    assert first.n_seeds_used == 1
    forced = propagate(img1, img2, pair, None, subpixel=False, seed_scores=[0.1, 0.9])
    assert forced.n_seeds_used == 1
    np.testing.assert_array_equal(forced.integer_matches[0, 2:], np.rint(pair[1, 2:]))
    with pytest.raises(StereoseedError):
        propagate(img1, img2, pair, None, seed_scores=[1.0])


def test_input_conversions_and_sizes(affine_pair):
    img1, img2, A, F, seeds = affine_pair
    ref = propagate(img1, img2, seeds, F, subpixel=False)
    # uint8 BGR images: same geometry, nearly the same matches (quantisation)
    u1 = cv2.cvtColor(np.rint(img1 * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    u2 = cv2.cvtColor(np.rint(img2 * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    res = propagate(u1, u2, seeds, F, subpixel=False)
    assert abs(res.n_matches - ref.n_matches) < 0.02 * ref.n_matches
    np.testing.assert_allclose(as_grey01(u1), np.rint(img1 * 255) / 255, atol=1e-12)
    np.testing.assert_allclose(as_grey01(np.dstack([img1] * 3)), img1, atol=1e-12)  # float BGR
    # images of different sizes: crop image 2 (its pixel grid keeps its origin)
    small = propagate(img1, img2[: H - 40, : W - 60], seeds, F, subpixel=False)
    assert small.match_x.shape == (H, W) and small.n_matches > 0.5 * ref.n_matches
    assert integer_x2(small)[:, 0].max() < W - 60 and integer_x2(small)[:, 1].max() < H - 40
    with pytest.raises(StereoseedError):
        propagate(img1[None], img2, seeds)
    with pytest.raises(StereoseedError):
        propagate(img1, img2, seeds[:, :3])
    with pytest.raises(StereoseedError):
        propagate(img1, img2, seeds, subpixel_method="cubic")


def test_disparity_image_and_png(affine_pair, tmp_path):
    img1, img2, A, F, seeds = affine_pair
    res = propagate(img1, img2, seeds, F)
    vis = disparity_image(res, img1.shape)
    assert vis.shape == (H, W, 3) and vis.dtype == np.uint8
    matched = res.match_x >= 0
    assert (vis[~matched] == 0).all()
    assert (vis[matched].max(axis=1) > 0).mean() > 0.99
    path = save_propagation_png(img1, res, tmp_path / "prop.png")
    back = cv2.imread(str(path))
    assert back.shape == (H, 2 * W, 3)
    np.testing.assert_array_equal(back[:, W:], vis)


# --------------------------------------------------------------------------------------------
# Pure-Python reference implementation, compared with the Numba kernel on tiny pairs
# --------------------------------------------------------------------------------------------


def reference_propagation(I1, I2, seeds, F, cfg):
    """The algorithm of paper.md written plainly (heapq, direct ZNCC); returns a set of integer
    matches (x1, y1, x2, y2)."""
    h = cfg.window // 2

    def texture(I):
        Hh, Ww = I.shape
        t = np.zeros(I.shape, bool)
        for y in range(Hh):
            for x in range(Ww):
                s = 0.0
                for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                    if 0 <= x + dx < Ww and 0 <= y + dy < Hh:
                        s = max(s, abs(I[y + dy, x + dx] - I[y, x]))
                t[y, x] = s > cfg.min_texture
        return t

    def window(I, x, y):
        if h <= x < I.shape[1] - h and h <= y < I.shape[0] - h:
            return I[y - h:y + h + 1, x - h:x + h + 1]
        return None

    def zncc(x1, y1, x2, y2):
        a, b = window(I1, x1, y1), window(I2, x2, y2)
        if a is None or b is None:
            return -1.0
        a, b = a - a.mean(), b - b.mean()
        na, nb = np.sum(a * a), np.sum(b * b)
        if na <= 1e-12 or nb <= 1e-12:
            return -1.0
        return float(np.sum(a * b) / np.sqrt(na * nb))

    tex1, tex2 = texture(I1), texture(I2)
    taken1, taken2, matches, heap = set(), set(), set(), []
    rs = [tuple(int(v) for v in np.rint(s)) for s in seeds]
    scored = sorted(((zncc(*s), k, s) for k, s in enumerate(rs)), key=lambda t: (-t[0], t[1]))
    for z, k, s in scored:
        if z > cfg.min_zncc and s[:2] not in taken1 and s[2:] not in taken2:
            taken1.add(s[:2]), taken2.add(s[2:]), matches.add(s)
            heapq.heappush(heap, (-z, len(matches), s))
    r, g = cfg.neighbourhood, cfg.disparity_gradient
    while heap:
        _, _, (x, y, xp, yp) = heapq.heappop(heap)
        cands = []
        for vy in range(-r, r + 1):
            for vx in range(-r, r + 1):
                u = (x + vx, y + vy)
                if u in taken1 or not (0 <= u[0] < I1.shape[1] and 0 <= u[1] < I1.shape[0]):
                    continue
                if not tex1[u[1], u[0]]:
                    continue
                for ey in range(-g, g + 1):
                    for ex in range(-g, g + 1):
                        v = (u[0] + xp - x + ex, u[1] + yp - y + ey)
                        if v in taken2 or not (0 <= v[0] < I2.shape[1] and 0 <= v[1] < I2.shape[0]):
                            continue
                        if not tex2[v[1], v[0]]:
                            continue
                        if F is not None:
                            l = F @ np.array([u[0], u[1], 1.0])
                            if abs(l @ np.array([v[0], v[1], 1.0])) / np.hypot(l[0], l[1]) > cfg.epipolar_band_px:
                                continue
                        z = zncc(*u, *v)
                        if z > cfg.min_zncc:
                            cands.append((z, u, v))
        for z, u, v in sorted(cands, key=lambda c: -c[0]):
            if u not in taken1 and v not in taken2:
                taken1.add(u), taken2.add(v), matches.add(u + v)
                heapq.heappush(heap, (-z, len(matches), u + v))
    return matches


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10_000), shift=st.tuples(st.integers(-2, 2), st.integers(-2, 2)),
       use_f=st.booleans())
def test_kernel_matches_reference(seed, shift, use_f):
    rng = np.random.default_rng(seed)
    I1 = multiscale_texture(22, 26, rng)
    I1[14:20, 3:9] = 0.5  # a flat patch
    dx, dy = shift
    # clipped: grey images are in [0, 1] (a float image above 1 would be read as 0..255)
    I2 = np.clip(np.roll(I1, (dy, dx), axis=(0, 1)) + rng.normal(0.0, 0.03, I1.shape), 0.0, 1.0)
    F = None
    if use_f and (dx, dy) != (0, 0):
        F = skew(np.array([dx, dy, 0.0]))  # lines through x1 along the displacement
    seeds = np.array([[8.0, 8.0, 8.0 + dx, 8.0 + dy], [17.0, 6.0, 17.0 + dx, 6.0 + dy]])
    cfg = PropagationConfig()
    res = propagate(I1, I2, seeds, F, cfg, subpixel=False)
    got = {tuple(int(v) for v in row) for row in res.integer_matches}
    assert got == reference_propagation(I1, I2, seeds, F, cfg)


# --------------------------------------------------------------------------------------------
# Rendered box scene (stereoseed.synthetic.scene)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_pair():
    synthetic = pytest.importorskip("stereoseed.synthetic.scene")
    from stereoseed.geometry.projection import fundamental_from_projections, project

    scene = synthetic.render_scene(synthetic.SceneConfig(n_images=2))
    I1, I2 = as_grey01(scene.images[0]), as_grey01(scene.images[1])
    pts, labels = scene.surface_points(0)
    Hs, Ws = labels.shape
    flat_pts = pts.reshape(-1, 3)
    fg = labels.ravel() >= 0
    covis = np.zeros(Hs * Ws, bool)
    covis[fg] = scene.is_visible(1, flat_pts[fg], margin=2.5)  # the 5x5 window fits in image 2
    gt = np.full((Hs * Ws, 2), np.nan)
    gt[covis] = project(scene.P[1], flat_pts[covis])
    # seeds: 100 true correspondences at pixel centres of image 0 on the box faces
    rng = np.random.default_rng(0)
    faces = np.flatnonzero(covis & (labels.ravel() >= 1))
    pick = rng.choice(faces, 100, replace=False)
    seeds = np.column_stack([pick % Ws, pick // Ws, gt[pick]]).astype(np.float64)
    F = fundamental_from_projections(scene.P[0], scene.P[1])
    target = covis.reshape(Hs, Ws) & texture_mask(I1, PropagationConfig().min_texture)
    return I1, I2, F, seeds, gt.reshape(Hs, Ws, 2), labels, target


def scene_figures(res: PropagationResult, gt, labels, target) -> dict:
    """Coverage of the textured co-visible pixels; median error and share within 1 px on the
    box faces and on the ground (matches whose pixel is occluded in image 2 count as errors)."""
    m = res.matches
    xi, yi = m[:, 0].astype(int), m[:, 1].astype(int)
    matched = np.zeros(labels.shape, bool)
    matched[yi, xi] = True
    err = np.linalg.norm(m[:, 2:] - gt[yi, xi], axis=1)
    err[~np.isfinite(err)] = np.inf  # matched, but the point is hidden in image 2
    lab = labels[yi, xi]
    out = {"n_matches": res.n_matches, "coverage": float((matched & target).sum() / target.sum())}
    for name, sel in (("faces", lab >= 1), ("ground", lab == 0), ("all", lab >= 0)):
        out[name] = {"n": int(sel.sum()), "median_px": float(np.median(err[sel])),
                     "within_1px": float(np.mean(err[sel] < 1.0))}
    return out


@pytest.mark.slow
def test_scene_coverage_and_accuracy(scene_pair, record_property):
    I1, I2, F, seeds, gt, labels, target = scene_pair
    figs = {}
    for method in ("none", "quadratic", "affine"):
        res = propagate(I1, I2, seeds, F, subpixel=method != "none",
                        subpixel_method="affine" if method == "none" else method)
        figs[method] = scene_figures(res, gt, labels, target)
        record_property(f"scene_{method}", figs[method])
    print(figs)
    none, quad, aff = figs["none"], figs["quadratic"], figs["affine"]
    assert none["coverage"] >= 0.80
    assert none["n_matches"] > 100_000
    # integer matches: the wide baseline (shear up to 1.3 px/px) leaves them ~1 px off
    assert none["all"]["median_px"] < 1.5
    # plain quadratic refinement helps but cannot undo the shear-induced bias
    assert quad["all"]["median_px"] < none["all"]["median_px"]
    # affine-adapted refinement: the targets of the brief, with margin
    assert aff["all"]["median_px"] <= 0.5
    for part in ("faces", "ground"):
        assert aff[part]["median_px"] <= 0.25, (part, aff[part])
        assert aff[part]["within_1px"] >= 0.90, (part, aff[part])


def test_scene_without_f_still_propagates(scene_pair):
    I1, I2, F, seeds, gt, labels, target = scene_pair
    res = propagate(I1, I2, seeds, None)
    figs = scene_figures(res, gt, labels, target)
    assert figs["coverage"] >= 0.80
    assert figs["all"]["median_px"] <= 0.5
    assert figs["all"]["within_1px"] >= 0.75


def test_quadratic_refinement_reads_no_window_leaving_image_2(monkeypatch):
    """A match whose 3x3 grid touches the border: the shifted windows that leave image 2 have
    inv2 = 0 and must not be read (the kernel ran off the array: a segfault on a Dask worker,
    where the image ended a memory mapping). Run in Python, where such a read raises."""
    from stereoseed.matching.propagation import refine as propagation_refine
    from stereoseed.matching.propagation._kernels import dot_window, window_stats

    rng = np.random.default_rng(3)
    half = 2
    I1, I2 = rng.uniform(0, 1, (2, 20, 24))
    mean1, inv1 = window_stats(I1, half)
    _, inv2 = window_stats(I2, half)
    # x2 one pixel inside each border: the centres of the 3x3 grid are in, some windows are not
    x1 = np.array([10, 10, 10, 12], np.int32)  # the last one well inside
    y1 = np.array([10, 10, 8, 9], np.int32)
    x2 = np.array([1, 22, 11, 12], np.int32)
    y2 = np.array([9, 9, 18, 9], np.int32)
    F = np.zeros((3, 3))
    compiled = propagation_refine.refine_quadratic(I1, mean1, inv1, I2, inv2, x1, y1, x2, y2, half, False, F)
    monkeypatch.setattr(propagation_refine, "dot_window", dot_window.py_func)
    python = propagation_refine.refine_quadratic.py_func(I1, mean1, inv1, I2, inv2, x1, y1, x2, y2, half, False, F)
    np.testing.assert_array_equal(python[0][:3], x2[:3])  # a window left image 2: x2 stays integer
    np.testing.assert_array_equal(python[1][:3], y2[:3])
    assert np.all(np.abs(python[0][3:] - x2[3:]) <= 1.0)  # refined within one pixel
    for got, want in zip(compiled, python):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


@pytest.mark.parametrize("use_f", [False, True])
def test_affine_refinement_in_bands_is_the_whole_images(affine_pair, use_f, monkeypatch):
    """Image 1 taken a few rows at a time (as a 24-megapixel image is, to bound memory) gives
    the same positions, bit for bit, as one band over the whole image: a fit reads only its
    band and the margin."""
    from stereoseed.matching.propagation import refine

    img1, img2, _, F, seeds = affine_pair
    whole = propagate(img1, img2, seeds, F if use_f else None, subpixel=True, subpixel_method="affine")
    monkeypatch.setattr(refine, "_BAND_PIXELS", 7 * W)  # 35 bands of 7 rows, narrower than the fit's window
    banded = propagate(img1, img2, seeds, F if use_f else None, subpixel=True, subpixel_method="affine")
    assert whole.n_matches > 10_000
    np.testing.assert_array_equal(banded.matches, whole.matches)
    np.testing.assert_array_equal(banded.refined_by, whole.refined_by)


@pytest.mark.parametrize("use_f", [False, True])
def test_bands_are_the_whole_image_under_a_large_vertical_disparity(use_f, monkeypatch):
    """Image 2 is image 1 moved 600.3 rows up (a walk along the image's y axis): the positions in
    a band far below image 2's are still the whole image's, bit for bit (each disparity is its
    position less its pixel's row in one subtraction, as over the whole image)."""
    from stereoseed.matching.propagation import refine

    rng = np.random.default_rng(11)
    img1 = multiscale_texture(1100, 96, rng)
    img2 = cv2.warpAffine(img1, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -600.3]]), (96, 1100), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
    x1 = np.column_stack([rng.uniform(10, 86, 30), rng.uniform(640, 1080, 30)])
    seeds = np.hstack([x1, x1 - [0.0, 600.3]])
    F = skew(np.array([0.0, 1.0, 0.0])) if use_f else None  # vertical epipolar lines
    monkeypatch.setattr(refine, "_BAND_PIXELS", 1 << 30)
    whole = propagate(img1, img2, seeds, F, subpixel=True, subpixel_method="affine")
    monkeypatch.setattr(refine, "_BAND_PIXELS", 341 * 96)  # a 3072 x 2048 image's bands
    banded = propagate(img1, img2, seeds, F, subpixel=True, subpixel_method="affine")
    assert whole.n_matches > 20_000 and np.count_nonzero(whole.refined_by == 2) > 10_000
    np.testing.assert_array_equal(banded.matches, whole.matches)
