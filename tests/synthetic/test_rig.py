"""The stereo rig walked round the synthetic box: its cameras, its images and the single-camera walk
over the same images."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from geometry_helpers import relative_pose
from test_synthetic import _dark_square_centroid, _grey

from stereoseed.features.image import to_gray
from stereoseed.geometry.projection import (
    camera_center,
    decompose_projection,
    rotation_angle_deg,
    viewing_direction,
)
from stereoseed.synthetic.rig import RigConfig, render_rig
from stereoseed.synthetic.scene import (
    SQUARE_GAP,
    SQUARE_SIZE,
    SceneConfig,
)

# 320 x 240 (3 x 3 samples a pixel: the squares' edges anti-aliased): the squares ~15 px wide, the gaps ~10 px
SMALL = SceneConfig().scaled(0.5)
TINY = replace(SceneConfig(), supersample=1).scaled(0.125)


@pytest.fixture(scope="module")
def plain_rig():
    return render_rig(RigConfig(stations=4, textured=False, view=SMALL))


@pytest.mark.parametrize("step, stations", [(30.0, 12), (45.0, 8)])
def test_every_station_holds_the_rig(step, stations):
    walk = render_rig(RigConfig(step_deg=step, stations=stations, textured=False, view=TINY))
    rig = walk.rig
    assert walk.stations == stations and len(walk.scene.images) == 2 * stations
    assert rig.baseline == pytest.approx(0.12, abs=1e-15)  # the scene is in metres: 12 cm
    assert rig.K_right[0, 0] / rig.K_left[0, 0] == pytest.approx(1.03, rel=1e-12)
    assert rig.K_right[1, 1] / rig.K_left[1, 1] == pytest.approx(1.03, rel=1e-12)
    azimuths = []
    for k in range(stations):
        P_left, P_right = walk.projections(k)
        R_rl, t_rl = relative_pose(P_left, P_right)
        np.testing.assert_allclose(R_rl, rig.R_rl, atol=1e-9)
        np.testing.assert_allclose(t_rl, rig.t_rl, atol=1e-9)
        np.testing.assert_allclose(decompose_projection(P_left)[0], rig.K_left, atol=1e-9)
        np.testing.assert_allclose(decompose_projection(P_right)[0], rig.K_right, atol=1e-9)
        C_left, C_right = camera_center(P_left), camera_center(P_right)
        assert np.linalg.norm(C_right - C_left) == pytest.approx(0.12, abs=1e-12)
        R_left = decompose_projection(P_left)[1]
        # the bar runs along the left camera's x axis (image right)
        np.testing.assert_allclose(R_left @ (C_right - C_left), [0.12, 0.0, 0.0], atol=1e-12)
        # turned in by 5 degrees about the image's vertical: the axes meet b / tan(5 deg) ahead
        d_left, d_right = viewing_direction(P_left), viewing_direction(P_right)
        assert np.degrees(np.arccos(np.clip(d_left @ d_right, -1, 1))) == pytest.approx(5.0, abs=1e-9)
        assert rotation_angle_deg(R_rl, np.eye(3)) == pytest.approx(5.0, abs=1e-9)
        a, b = np.linalg.lstsq(np.stack([d_left, -d_right], axis=1), C_right - C_left, rcond=None)[0]
        np.testing.assert_allclose(C_left + a * d_left, C_right + b * d_right, atol=1e-12)
        assert a == pytest.approx(0.12 / np.tan(np.radians(5.0)), rel=1e-9)
        azimuths.append(np.degrees(np.arctan2(C_left[1], C_left[0])))
    steps = np.diff(np.unwrap(np.radians(azimuths))) * 180 / np.pi
    np.testing.assert_allclose(steps, step, atol=2.0)  # the ring's placement, jittered


def test_the_images_show_the_plain_box_where_the_cameras_say(plain_rig):
    """Every image's dark squares lie where its camera projects them (their darkness-weighted
    centroids, test_synthetic's measure: a camera of the other side is ~4 px off), the gaps
    between them are light."""
    scene = plain_rig.scene
    squares = scene.corners.reshape(-1, 4, 3)  # counter-clockwise from the (min s, min r) corner
    s_axis = (squares[:, 1] - squares[:, 0]) / SQUARE_SIZE
    in_gap = squares.mean(axis=1) - (SQUARE_SIZE + SQUARE_GAP) / 2 * s_axis  # the gap left of each square
    for i in range(scene.n_images):
        seen = np.flatnonzero(scene.corner_visibility(i).reshape(-1, 4).all(axis=1))
        found = [_dark_square_centroid(_grey(scene.images[i]), scene.project(i, squares[q])) for q in seen]
        offsets = [np.linalg.norm(expected - measured) for expected, measured in filter(None, found)]
        assert len(offsets) >= 10
        assert np.median(offsets) < 0.05 and np.max(offsets) < 0.2, (i, offsets)
        uv = np.rint(scene.project(i, in_gap[seen])).astype(int)
        assert np.all(to_gray(scene.images[i])[uv[:, 1], uv[:, 0]] > 0.45)


def test_the_single_camera_walk_is_the_pair_then_the_right_camera(plain_rig):
    walk = plain_rig.single_camera_walk()
    assert walk.n_images == plain_rig.stations + 1 and walk.config.n_images == walk.n_images
    assert walk.images[0] is plain_rig.images(0)[0]
    for k in range(plain_rig.stations):
        assert walk.images[k + 1] is plain_rig.images(k)[1]
        np.testing.assert_array_equal(walk.P[k + 1], plain_rig.projections(k)[1])
        assert walk.names[k + 1] == f"right_{k:03d}.png"
    for got, expected in zip(walk.calibration_points(), plain_rig.scene.calibration_points()):
        np.testing.assert_array_equal(got, expected)  # the same calibrated pair


def test_the_first_station_calibrates_to_the_rig(plain_rig):
    left, right = plain_rig.calibration()
    assert left.n_points >= 40 and left.rms_px < 0.2 and right.rms_px < 0.2  # 0.1 px of noise on each corner
    for cal, P in zip((left, right), plain_rig.projections(0)):
        assert np.linalg.norm(camera_center(cal.P) - camera_center(P)) < 0.01
    calibrated, truth = plain_rig.calibrated_rig(), plain_rig.rig
    # two DLT calibrations from 0.1 px corners on 320 x 240 images: a few tenths of a degree
    assert calibrated.baseline == pytest.approx(truth.baseline, rel=0.03)
    assert rotation_angle_deg(calibrated.R_rl, truth.R_rl) < 0.6
    assert calibrated.K_right[0, 0] / calibrated.K_left[0, 0] == pytest.approx(1.03, rel=0.015)


def test_noise_is_added_to_every_image():
    config = RigConfig(stations=1, view=TINY)  # one station: the calibrated pair alone
    clean, noisy = render_rig(config), render_rig(replace(config, noise_sigma=3.0))
    assert noisy.scene.n_images == 2
    for a, b in zip(clean.scene.images, noisy.scene.images):
        assert np.std(b.astype(float) - a) == pytest.approx(3.0, rel=0.1)
    for a, b in zip(noisy.scene.images[0::2], noisy.scene.images[1::2]):
        assert not np.array_equal(a, b)


def test_bad_settings_are_refused():
    for bad in ({"baseline": 0.0}, {"toe_in_deg": 50.0}, {"stations": 0}, {"focal_ratio": -1.0},
                {"noise_sigma": -1.0}):
        with pytest.raises(ValueError):
            RigConfig(**bad)
