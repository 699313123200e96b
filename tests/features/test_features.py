"""Interest points and ZNCC descriptors (stereoseed.features.harris)."""
from __future__ import annotations

import logging
import warnings

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from stereoseed.config import FeatureConfig
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import (
    Features,
    describe,
    describe_scaled,
    detect_corners,
    detect_corners_with_response,
    extract_features,
    to_gray,
)

from geometry_helpers import band_noise


# --- test images with known geometry ---------------------------------------------------------
def checkerboard(
    shape: tuple[int, int], H: np.ndarray, cell: float = 20.0, ss: int = 8
) -> np.ndarray:
    """Anti-aliased checkerboard seen through homography H (board -> image), (H, W) float32.

    Rendered analytically with ss x ss supersampling: pixel (u, v) covers [u-0.5, u+0.5]^2, so
    its centre is (u, v) as in the package's convention.
    """
    h, w = shape
    o = (np.arange(ss) + 0.5) / ss - 0.5
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    acc = np.zeros(shape)
    Hinv = np.linalg.inv(H)
    for dy in o:
        for dx in o:
            p = np.stack([u + dx, v + dy, np.ones_like(u)], axis=-1) @ Hinv.T
            bx, by = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
            acc += (np.floor(bx / cell) + np.floor(by / cell)) % 2
    return (0.2 + 0.6 * acc / ss**2).astype(np.float32)


def board_homography(angle_deg: float = 17.0, shift=(31.3, 27.6)) -> np.ndarray:
    a = np.radians(angle_deg)
    H = np.array([[np.cos(a), -np.sin(a), shift[0]], [np.sin(a), np.cos(a), shift[1]], [0, 0, 1]])
    H[2, :2] = [2e-4, -1e-4]  # a little perspective
    return H


def board_corners(H: np.ndarray, shape: tuple[int, int], cell: float = 20.0) -> np.ndarray:
    """Image positions (K, 2) of the board's inner corners that fall well inside the image."""
    g = np.arange(-20, 40) * cell
    bx, by = np.meshgrid(g, g)
    pts = np.stack([bx.ravel(), by.ravel(), np.ones(bx.size)], axis=1) @ H.T
    xy = pts[:, :2] / pts[:, 2:]
    h, w = shape
    inside = (xy[:, 0] > 15) & (xy[:, 0] < w - 16) & (xy[:, 1] > 15) & (xy[:, 1] < h - 16)
    return xy[inside]


def dark_squares_on_texture(shape: tuple[int, int] = (240, 320), side: float = 16.0, pitch: float = 36.0,
                            angle_deg: float = 12.0, ss: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Dark squares on a strong smooth texture (the synthetic box's pattern, in 2-D), anti-aliased
    by ss x ss supersampling in the package's pixel convention: (image (H, W) float32, true
    square corners (K, 2) well inside the image)."""
    h, w = shape
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    o = (np.arange(ss) + 0.5) / ss - 0.5
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    cover = np.zeros(shape)
    for dy in o:
        for dx in o:
            x, y = u + dx - 20.0, v + dy - 20.0
            bx, by = c * x + s * y, -s * x + c * y  # board frame
            cover += (np.mod(bx, pitch) < side) & (np.mod(by, pitch) < side) & (bx > 0) & (by > 0)
    cover /= ss * ss
    img = (0.3 + 0.7 * band_noise(shape)) * (1 - cover) + 0.06 * cover
    g = np.arange(12) * pitch
    bx, by = np.meshgrid(np.concatenate([g, g + side]), np.concatenate([g, g + side]))
    corners = np.stack([c * bx - s * by + 20.0, s * bx + c * by + 20.0], axis=-1).reshape(-1, 2)
    inside = (corners[:, 0] > 15) & (corners[:, 0] < w - 16) & (corners[:, 1] > 15) & (corners[:, 1] < h - 16)
    return img.astype(np.float32), corners[inside]


# --- to_gray ---------------------------------------------------------------------------------
def test_to_gray_dtypes_and_channels():
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (12, 9, 3), dtype=np.uint8)
    g = to_gray(bgr)
    assert g.dtype == np.float32 and g.shape == (12, 9)
    expected = cv2.cvtColor(bgr.astype(np.float32) / 255.0, cv2.COLOR_BGR2GRAY)
    np.testing.assert_allclose(g, expected, atol=1e-6)
    np.testing.assert_allclose(to_gray(bgr[:, :, 0]), bgr[:, :, 0] / 255.0, atol=1e-6)
    np.testing.assert_allclose(to_gray(bgr[:, :, :1]), bgr[:, :, 0] / 255.0, atol=1e-6)
    bgra = np.dstack([bgr, np.full((12, 9), 7, np.uint8)])
    np.testing.assert_allclose(to_gray(bgra), g, atol=1e-6)
    np.testing.assert_allclose(to_gray(bgr.astype(np.uint16) * 257), g, atol=1e-5)
    # Floats are taken in [0, 1]; above 1 they are read as 0..255.
    np.testing.assert_allclose(to_gray(bgr.astype(np.float64) / 255.0), g, atol=1e-6)
    np.testing.assert_allclose(to_gray(bgr.astype(np.float64)), g, atol=1e-5)
    weird = np.array([[np.nan, -1.0], [0.5, np.inf]])
    out = to_gray(weird)
    assert np.all(np.isfinite(out)) and out.min() >= 0 and out.max() <= 1


@pytest.mark.parametrize("shape", [(5,), (4, 4, 2), (2, 3, 4, 5)])
def test_to_gray_rejects_bad_shapes(shape):
    with pytest.raises(StereoseedError):
        to_gray(np.zeros(shape, np.uint8))


# --- detection -------------------------------------------------------------------------------
def test_detect_corners_contract():
    cfg = FeatureConfig(max_corners=300, min_distance=7.0, border=10)
    gray = band_noise((200, 260))
    pts, resp = detect_corners_with_response(gray, cfg)
    assert pts.dtype == np.float64 and pts.shape[1] == 2
    assert 0 < len(pts) <= 300
    assert np.all(np.diff(resp) <= 0), "strongest first"
    assert np.all(resp > 0)
    b = cfg.border
    assert np.all((pts >= b) & (pts <= np.array([260 - 1 - b, 200 - 1 - b])))
    # Spacing holds at detection; sub-pixel refinement moves a point by about a pixel at most.
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d.min() > cfg.min_distance - 2.0
    np.testing.assert_array_equal(detect_corners(gray, cfg), pts)


def test_detect_corners_subpixel_on_junctions():
    """Checkerboard corners (junctions) are found to a small fraction of a pixel."""
    shape = (240, 320)
    H = board_homography()
    img = checkerboard(shape, H)
    truth = board_corners(H, shape)
    pts = detect_corners(img, FeatureConfig(min_distance=8.0))
    d = np.linalg.norm(truth[:, None] - pts[None], axis=2)
    nearest = d.min(axis=1)
    assert np.mean(nearest < 1.0) > 0.95, "almost every inner corner is detected"
    assert np.median(nearest) < 0.08
    assert np.percentile(nearest[nearest < 1.0], 95) < 0.15
    # The Harris peak alone is biased at junctions (~0.4 px here): cornerSubPix took over.
    peak_only = detect_corners(img, FeatureConfig(min_distance=8.0, subpixel_window=0))
    d_peak = np.linalg.norm(truth[:, None] - peak_only[None], axis=2).min(axis=1)
    assert np.median(d_peak) > 3 * np.median(nearest)


def test_detect_corners_subpixel_on_square_corners_over_texture():
    """A dark square's corner on a strong texture: the window as a whole fits the junction model
    loosely, its strong edges tightly; cornerSubPix is kept there (the Harris peak sits ~1 px
    inside the corner). Measured: 93 % within 0.5 px, median 0.25 px (55 % and 0.38 px when the
    whole window alone decides)."""
    img, truth = dark_squares_on_texture()
    pts = detect_corners(img, FeatureConfig())
    nearest = np.linalg.norm(truth[:, None] - pts[None], axis=2).min(axis=1)
    assert len(truth) > 100
    assert np.mean(nearest < 0.5) > 0.85
    assert np.median(nearest) < 0.3


@pytest.mark.parametrize("blur, within", [(0.0, 0.9), (0.7, 0.75)])
def test_square_corners_meet_where_their_edges_do(blur, within):
    """The same squares: moved to the intersection of their two edges, the corners land within
    0.2 px of the truth for 98 % of them, median 0.06 px (cornerSubPix alone: 37 %, 0.25 px);
    blurred by a 0.7 px Gaussian (a real lens): 85 %, 0.11 px (cornerSubPix: 30 %, 0.30 px)."""
    img, truth = dark_squares_on_texture()
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    errors = {}
    for edge_corners in (False, True):
        pts = detect_corners(img, FeatureConfig(edge_corners=edge_corners))
        errors[edge_corners] = np.linalg.norm(truth[:, None] - pts[None], axis=2).min(axis=1)
    assert np.mean(errors[True] < 0.2) > within
    assert np.median(errors[True]) < 0.15 < np.median(errors[False])


def _junction_residual_numpy(gx, gy, q, win, strong_fraction=0.0):
    """The junction residual's formula in NumPy: sum (g . (q - p))^2 / sum |g|^2 |q - p|^2."""
    h, w = gx.shape
    qi = np.rint(q).astype(np.int64)
    qi[:, 0] = np.clip(qi[:, 0], win, w - 1 - win)
    qi[:, 1] = np.clip(qi[:, 1], win, h - 1 - win)
    dy, dx = np.meshgrid(np.arange(-win, win + 1), np.arange(-win, win + 1), indexing="ij")
    g_x = gx[qi[:, 1:2] + dy.reshape(1, -1), qi[:, 0:1] + dx.reshape(1, -1)]
    g_y = gy[qi[:, 1:2] + dy.reshape(1, -1), qi[:, 0:1] + dx.reshape(1, -1)]
    vx = (q[:, 0:1] - qi[:, 0:1] - dx.reshape(1, -1)).astype(np.float32)
    vy = (q[:, 1:2] - qi[:, 1:2] - dy.reshape(1, -1)).astype(np.float32)
    g2 = g_x * g_x + g_y * g_y
    along, full = (g_x * vx + g_y * vy) ** 2, g2 * (vx * vx + vy * vy)
    if strong_fraction > 0:
        weak = g2 < np.float32(strong_fraction**2) * g2.max(axis=1, keepdims=True)
        along[weak], full[weak] = 0.0, 0.0
    num, den = along.sum(axis=1, dtype=np.float64), full.sum(axis=1, dtype=np.float64)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)


@pytest.mark.parametrize("win", [5, 3, 2])
@pytest.mark.parametrize("strong_fraction", [0.0, 0.5])
def test_junction_residual_kernel_is_the_numpy_formula_bit_for_bit(win, strong_fraction):
    """The compiled residual sums as NumPy does: the interest points of the default windows
    did not move when it replaced NumPy (points near and on the border included)."""
    from stereoseed.features.harris import _junction_residual

    img, _ = dark_squares_on_texture()
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    rng = np.random.default_rng(win)
    h, w = img.shape
    q = np.vstack([rng.uniform([0, 0], [w - 1, h - 1], (500, 2)), [[0, 0], [w - 1, h - 1], [-3, 5], [w + 2, 7]]])
    got = _junction_residual(gx, gy, q, win, strong_fraction)
    assert np.array_equal(got, _junction_residual_numpy(gx, gy, q, win, strong_fraction))
    assert np.all((got >= 0) & (got <= 1))


def test_junction_residual_is_zero_at_an_ideal_junction_and_grows_off_it():
    from stereoseed.features.harris import _junction_residual

    img = np.zeros((64, 64), np.float32)
    img[32:, 32:] = 1.0  # a square's corner: the edges meet at (31.5, 31.5)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    at, *off = _junction_residual(gx, gy, np.array([[31.5, 31.5], [32, 32], [33.5, 32.5], [35, 31.5]]), 5)
    assert at < 0.05 < off[0] < 0.2 < off[1] < off[2]  # the blur rounds the apex: not exactly 0


def test_one_interest_point_per_position():
    # two Harris maxima of one corner (its two arms) refine to the same point: kept once
    img, _ = dark_squares_on_texture()
    pts = detect_corners(img)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d.min() >= 0.5


def test_detect_corners_repeatable_under_subpixel_shift():
    """On texture (no junctions) the Harris-peak refinement follows a sub-pixel translation."""
    big = band_noise((260, 340), seed=3)
    shift = np.array([0.37, -0.61])
    M = np.array([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(big, M, (340, 260), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    a = detect_corners(big[20:-20, 20:-20])[:200]  # the strongest: weak maxima are unstable
    b = detect_corners(moved[20:-20, 20:-20])
    d = np.linalg.norm((a + shift)[:, None] - b[None], axis=2)
    nearest = d.min(axis=1)
    close = nearest < 1.0
    assert close.mean() > 0.85
    # Harris at this scale on 1-2 px blobs is good to ~0.15 px; matches are then aligned to
    # ~0.03 px by stereoseed.matching.alignment.align_matches.
    assert np.median(nearest[close]) < 0.2


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((0, 0), np.float32),
        np.zeros((10, 10), np.float32),  # smaller than twice the border
        np.full((120, 160), 0.5, np.float32),  # flat
    ],
)
def test_detect_corners_empty_or_flat_logs(image, caplog):
    caplog.set_level(logging.INFO, logger="stereoseed.features.harris")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a log record, not a warning
        pts = detect_corners(image)
    assert pts.shape == (0, 2) and pts.dtype == np.float64
    assert any("no interest points" in r.getMessage() for r in caplog.records)


def test_detect_corners_rejects_colour():
    with pytest.raises(StereoseedError):
        detect_corners(np.zeros((50, 50, 3), np.float32))


# --- descriptors -----------------------------------------------------------------------------
def test_describe_is_normalised_and_invariant_to_gain_and_bias():
    gray = band_noise((80, 90), seed=5)
    pts = np.array([[20.3, 30.7], [45.0, 40.0], [60.5, 25.25]])
    desc, valid = describe(gray, pts, 11)
    assert desc.shape == (3, 121) and desc.dtype == np.float32 and valid.all()
    np.testing.assert_allclose(desc.mean(axis=1), 0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(desc, axis=1), 1, atol=1e-5)
    desc2, _ = describe(0.5 * gray + 0.2, pts, 11)
    np.testing.assert_allclose(desc2, desc, atol=1e-5)
    # The dot product is the ZNCC, 1 with itself.
    np.testing.assert_allclose(np.einsum("ij,ij->i", desc, desc), 1, atol=1e-5)


def test_describe_samples_subpixel_positions_bilinearly():
    # On a plane of grey levels bilinear interpolation is exact: the patch at (x, y) is the
    # plane sampled at (x + dx, y + dy), whatever the sub-pixel part of (x, y).
    v, u = np.mgrid[0:40, 0:50].astype(np.float32)
    plane = (0.01 * u + 0.004 * v + 0.1).astype(np.float32)
    pts = np.array([[20.25, 17.75]])
    desc, valid = describe(plane, pts, 5)
    d = np.arange(-2, 3)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    expect = 0.01 * (20.25 + dx) + 0.004 * (17.75 + dy)
    expect = (expect - expect.mean()).ravel()
    np.testing.assert_allclose(desc[0], expect / np.linalg.norm(expect), atol=2e-3)
    assert valid[0]


def test_describe_marks_flat_outside_and_nan_invalid():
    gray = band_noise((60, 60))
    gray[:, :25] = 0.3  # a flat region
    pts = np.array([[10.0, 30.0], [2.0, 30.0], [np.nan, 5.0], [40.0, 30.0], [57.0, 57.0]])
    desc, valid = describe(gray, pts, 11)
    np.testing.assert_array_equal(valid, [False, False, False, True, False])
    assert np.all(desc[~valid] == 0)
    with pytest.raises(StereoseedError):
        describe(gray, pts, 10)
    d0, v0 = describe(gray, np.zeros((0, 2)), 11)
    assert d0.shape == (0, 121) and v0.shape == (0,)


def test_describe_scaled_matches_a_zoomed_copy():
    gray = band_noise((200, 200), seed=9)
    zoom = 1.25  # the second image is the first magnified about (100, 100)
    M = np.array([[zoom, 0, 100 * (1 - zoom)], [0, zoom, 100 * (1 - zoom)]])
    big = cv2.warpAffine(gray, M, (200, 200), flags=cv2.INTER_CUBIC)
    pts = np.array([[90.0, 95.0], [110.5, 104.25], [99.0, 120.0]])
    d1, _ = describe(gray, pts, 11)
    same, _ = describe(big, 100 + zoom * (pts - 100), 11)
    scaled, _ = describe_scaled(big, 100 + zoom * (pts - 100), 11, zoom)
    z_same = np.einsum("ij,ij->i", d1, same)
    z_scaled = np.einsum("ij,ij->i", d1, scaled)
    assert np.all(z_scaled > 0.97)
    assert np.all(z_scaled > z_same)


def test_extract_features_bundles_everything():
    img = (band_noise((120, 150)) * 255).astype(np.uint8)
    f = extract_features(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), patch_size=9)
    assert isinstance(f, Features)
    n = len(f)
    assert n > 0
    assert f.points.shape == (n, 2) and f.desc.shape == (n, 81) and f.valid.shape == (n,)
    assert f.response.shape == (n,) and f.image_shape == (120, 150) and f.patch_size == 9
    assert f.gray is not None and f.gray.shape == (120, 150)
    assert f.valid.mean() > 0.9


# --- robustness ------------------------------------------------------------------------------
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    image=hnp.arrays(
        dtype=np.float32,
        shape=st.tuples(st.integers(0, 48), st.integers(0, 48)),
        elements=st.floats(0, 1, width=32),
    ),
    as_uint8=st.booleans(),
    max_corners=st.integers(1, 200),
    border=st.integers(0, 12),
    window=st.integers(0, 6),
)
def test_extract_features_never_crashes(image, as_uint8, max_corners, border, window):
    if as_uint8:
        image = (image * 255).astype(np.uint8)
    cfg = FeatureConfig(
        max_corners=max_corners, border=border, subpixel_window=window, min_distance=2.0
    )
    f = extract_features(image, cfg, patch_size=5)
    n = len(f)
    assert f.points.shape == (n, 2) and f.desc.shape == (n, 25) and n <= max_corners
    assert np.all(np.isfinite(f.points)) and np.all(np.isfinite(f.desc))
    if n:
        h, w = image.shape
        assert np.all((f.points >= 0) & (f.points <= np.array([w - 1, h - 1])))


@settings(max_examples=40, deadline=None)
@given(
    points=hnp.arrays(
        np.float64,
        st.tuples(st.integers(0, 30), st.just(2)),
        elements=st.floats(-50, 150) | st.just(np.nan) | st.just(np.inf),
    ),
    patch=st.sampled_from([3, 5, 11]),
)
def test_describe_never_crashes_on_any_points(points, patch):
    gray = band_noise((64, 96), seed=2)
    desc, valid = describe(gray, points, patch)
    assert desc.shape == (len(points), patch * patch) and valid.shape == (len(points),)
    assert np.all(np.isfinite(desc))
    if valid.any():
        np.testing.assert_allclose(np.linalg.norm(desc[valid], axis=1), 1, atol=1e-4)


def test_descriptors_are_the_same_whatever_opencv_s_remap_does(monkeypatch):
    """OpenCV 4.x's remap rounds a position to 1/32 px, 5.x's does not; where remap rounds, the
    patches come from sample_bilinear: the same descriptors (to float32 rounding) either way,
    and the exact bilinear values, not 1/32 px steps."""
    from stereoseed.features import harris

    gray = band_noise((60, 70), seed=7)
    pts = np.array([[20.3, 30.71], [45.0, 40.0], [33.53, 25.26], [1.2, 58.7]])
    monkeypatch.setattr(harris, "_remap_is_exact", lambda: False)
    mine, _ = describe(gray, pts, 11)
    ramp = np.tile(np.arange(8, dtype=np.float32), (8, 1))  # grey level = x
    row = harris._bilinear_patches(ramp, np.array([[3.3, 3.0]]), 3)[0, :3]
    np.testing.assert_allclose(row, [2.3, 3.3, 4.3], atol=1e-5)  # 1/32 px steps give 2.3125
    monkeypatch.undo()
    if harris._remap_is_exact():  # OpenCV 5.x: its remap is the oracle
        theirs, _ = describe(gray, pts, 11)
        np.testing.assert_allclose(mine, theirs, atol=1e-6)
