"""The lens model (stereoseed.geometry.lens) against OpenCV as an oracle, and its round trips."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereoseed.geometry.lens import (
    distort_normalized,
    distort_pixels,
    lens_coefficients,
    principal_r2,
    project_distorted,
    undistort_image,
    undistort_normalized,
    undistort_pixels,
    undistortion_maps,
)

from geometry_helpers import opencv_undistort_points

LENS = (-0.12, 0.03, 0.001, -0.0005)
LENSES = [LENS, (-0.3, 0.1, 0.002, -0.001, -0.02), (0.3, -0.05, -0.002, 0.001, 0.01),
          (0.15, 0.0, 0.0, 0.0)]
K = np.array([[800.0, 0.0, 323.5], [0.0, 790.0, 237.0], [0.0, 0.0, 1.0]])
K_SKEW = np.array([[800.0, 4.0, 323.5], [0.0, 790.0, 237.0], [0.0, 0.0, 1.0]])


def _frame_pixels(step: float = 8.0) -> np.ndarray:
    """A grid over a 640 x 480 frame, its border pixels included. -> (N, 2)."""
    u = np.append(np.arange(-0.5, 639.5, step), 639.5)
    v = np.append(np.arange(-0.5, 479.5, step), 479.5)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def _pose(rng):
    R, _ = cv2.Rodrigues(rng.uniform(-0.3, 0.3, size=3))
    return R, rng.uniform(-0.2, 0.2, size=3)


def test_coefficients():
    np.testing.assert_array_equal(lens_coefficients(()), np.zeros(5))
    np.testing.assert_array_equal(lens_coefficients(LENS), [*LENS, 0.0])
    with pytest.raises(ValueError, match="4 or 5"):
        lens_coefficients((0.1, 0.2))
    with pytest.raises(ValueError, match="finite"):
        lens_coefficients((0.1, np.nan, 0, 0))


def test_distort_normalized_formula():
    k1, k2, p1, p2, k3 = -0.2, 0.05, 0.003, -0.002, 0.01
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    c = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    expected = [x * c + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * c + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y]
    np.testing.assert_allclose(distort_normalized([[x, y]], (k1, k2, p1, p2, k3))[0], expected,
                               rtol=0, atol=1e-15)
    # No lens: the identity, and undistortion too.
    xy = np.array([[0.1, 0.2], [-0.4, 0.3]])
    np.testing.assert_array_equal(distort_normalized(xy, ()), xy)
    np.testing.assert_array_equal(undistort_normalized(xy, ()), xy)


@pytest.mark.parametrize("d", LENSES)
def test_project_distorted_equals_opencv_project_points(d):
    rng = np.random.default_rng(1)
    R, t = _pose(rng)
    # Points spread over (and a little beyond) the frame, 0.5 .. 3 units in front.
    z = rng.uniform(0.5, 3.0, 500)
    xy = rng.uniform(-0.5, 0.5, (500, 2)) * z[:, None]
    X_cam = np.column_stack([xy, z])
    points = (X_cam - t) @ R  # world = R^T (X_cam - t)
    ours = project_distorted(K, R, t, d, points)
    cv, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, K, np.array(lens_coefficients(d)))
    err = np.abs(ours - cv.reshape(-1, 2)).max()
    assert err < 1e-9, err


@pytest.mark.parametrize("d", LENSES)
def test_undistort_pixels_equals_opencv_undistort_points(d):
    pix = _frame_pixels()
    ours = undistort_pixels(pix, K, d)
    cv = opencv_undistort_points(pix, K, lens_coefficients(d), K,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15))
    err = np.abs(ours - cv).max()
    assert err < 1e-6, err


@pytest.mark.parametrize("d", LENSES)
@pytest.mark.parametrize("Kc", [K, K_SKEW], ids=["K", "skew"])
def test_round_trips_over_a_640x480_frame(d, Kc):
    pix = _frame_pixels(4.0)
    xy_d = np.column_stack([(pix[:, 0] - Kc[0, 2]) / Kc[0, 0], (pix[:, 1] - Kc[1, 2]) / Kc[1, 1]])
    # undistort(distort) and distort(undistort) in normalized units.
    back = distort_normalized(undistort_normalized(xy_d, d), d)
    assert np.abs(back - xy_d).max() < 1e-10
    xy = undistort_normalized(distort_normalized(xy_d, d), d)
    assert np.abs(xy - xy_d).max() < 1e-10
    # In pixels, through K (and its skew).
    und = undistort_pixels(pix, Kc, d)
    assert np.all(np.isfinite(und))
    assert np.abs(distort_pixels(und, Kc, d) - pix).max() < 1e-7
    assert np.abs(undistort_pixels(distort_pixels(pix, Kc, d), Kc, d) - pix).max() < 1e-7


def test_skew_is_honoured():
    # The lens acts on K^-1 pixels: a skewed K moves the undistorted pixel accordingly.
    pix = np.array([[10.0, 20.0], [600.0, 450.0]])
    und = undistort_pixels(pix, K_SKEW, LENS)
    Kinv = np.linalg.inv(K_SKEW)
    xy_d = (np.column_stack([pix, np.ones(2)]) @ Kinv.T)[:, :2]
    xy = undistort_normalized(xy_d, LENS)
    np.testing.assert_allclose(und, (np.column_stack([xy, np.ones(2)]) @ K_SKEW.T)[:, :2],
                               atol=1e-9)
    R, t = np.eye(3), np.zeros(3)
    X = np.column_stack([xy, np.ones(2)]) * 2.0
    np.testing.assert_allclose(project_distorted(K_SKEW, R, t, LENS, X), pix, atol=1e-9)


def test_undistort_is_nan_where_no_inverse():
    # Barrel lens k1 = -0.3: r_d = r (1 - 0.3 r^2) peaks at r_d ~ 0.70; beyond, no inverse.
    out = undistort_normalized([[1.0, 0.0], [0.3, 0.1]], (-0.3, 0.0, 0.0, 0.0))
    assert np.all(np.isnan(out[0])) and np.all(np.isfinite(out[1]))


@pytest.mark.parametrize("Kc", [K, K_SKEW], ids=["K", "skew"])
def test_undistortion_maps_sample_the_distorted_pixel(Kc):
    mx, my = undistortion_maps(Kc, LENS, (640, 480))
    assert mx.shape == (480, 640) and mx.dtype == np.float32
    pix = _frame_pixels(16.0)[:, :]
    pix = pix[(pix[:, 0] >= 0) & (pix[:, 1] >= 0)]
    u, v = pix[:, 0].astype(int), pix[:, 1].astype(int)
    src = np.column_stack([mx[v, u], my[v, u]])
    np.testing.assert_allclose(src, distort_pixels(np.column_stack([u, v]), Kc, LENS), atol=1e-3)


def test_undistort_image_gives_the_pinhole_image():
    # A distorted image of dots at known pinhole positions: after undistort_image the dots sit
    # at their pinhole pixels.
    h, w = 480, 640
    rng = np.random.default_rng(3)
    pinhole = np.column_stack([rng.uniform(60, w - 60, 20), rng.uniform(60, h - 60, 20)])
    # Render the distorted image analytically: pixel (x, y) shows the undistorted scene there.
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    und = undistort_pixels(np.column_stack([u.ravel(), v.ravel()]), K, LENS).reshape(h, w, 2)
    image = np.zeros((h, w), np.float64)
    for p in pinhole:
        image += np.exp(-((und[..., 0] - p[0]) ** 2 + (und[..., 1] - p[1]) ** 2) / (2 * 2.0**2))
    image = (image * 200).astype(np.float32)
    maps = undistortion_maps(K, LENS, (w, h))
    out = undistort_image(image, K, LENS, maps=maps)
    assert out.shape == image.shape and out.dtype == image.dtype
    np.testing.assert_array_equal(out, undistort_image(image, K, LENS))
    for p in pinhole:
        u0, v0 = np.rint(p).astype(int)
        win = out[v0 - 6:v0 + 7, u0 - 6:u0 + 7].astype(np.float64)
        yy, xx = np.mgrid[-6:7, -6:7]
        c = np.array([(win * xx).sum(), (win * yy).sum()]) / win.sum() + [u0, v0]
        assert np.abs(c - p).max() < 0.05, (c, p)


def test_principal_radius():
    assert principal_r2(()) == np.inf and principal_r2((0.1, 0.0, 0.0, 0.0)) == np.inf
    np.testing.assert_allclose(principal_r2((-0.3, 0.0, 0.0, 0.0)), 1 / 0.9, rtol=1e-12)
    s = principal_r2(LENS)  # 1 - 0.36 s + 0.15 s^2 has no positive root
    assert s == np.inf
    s = principal_r2((-0.3, 0.01, 0, 0, 0.001))
    np.testing.assert_allclose(1 - 0.9 * s + 0.05 * s**2 + 0.007 * s**3, 0.0, atol=1e-12)
