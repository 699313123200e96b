"""The Camera value type and the CameraModel parameterisations."""
import numpy as np
import pytest

from geometry_helpers import ring_camera
from stereoseed.geometry import Camera, CameraModel
from stereoseed.geometry.projection import camera_center, decompose_projection, project


def test_a_camera_keeps_its_P_bit_for_bit_and_decomposes_it_once():
    P = ring_camera(25.0)[3] * 3.7  # any scale
    cam = Camera(P)
    assert np.array_equal(cam.P, P) and not cam.P.flags.writeable
    K, R, t = decompose_projection(P)
    assert np.array_equal(cam.K, K) and np.array_equal(cam.R, R) and np.array_equal(cam.t, t)
    assert cam.K is cam.K  # cached
    np.testing.assert_allclose(cam.centre, camera_center(P))
    X = np.random.default_rng(0).normal(scale=0.1, size=(20, 3))
    np.testing.assert_array_equal(cam.project(X), project(P, X))
    with pytest.raises(ValueError):
        cam.P[0, 0] = 1.0


def test_from_krt_composes_and_keeps_the_given_factors():
    K, R, t, _ = ring_camera(40.0)
    cam = Camera.from_krt(K, R, t, CameraModel.ZERO_SKEW)
    assert cam.model is CameraModel.ZERO_SKEW
    np.testing.assert_array_equal(cam.K, K)
    np.testing.assert_allclose(cam.P, K @ np.hstack([R, t.reshape(3, 1)]))


@pytest.mark.parametrize("model", list(CameraModel))
def test_params_round_trip_under_every_model(model):
    K, R, t, P = ring_camera(70.0)
    cam = Camera(P, model)
    params = cam.params(reference_K=K)
    assert params.shape == (model.n_params,) and model.n_params == model.n_intrinsics + 6
    back = Camera.from_params(params, model, reference_K=K)
    np.testing.assert_allclose(back.P / np.linalg.norm(back.P), P / np.linalg.norm(P), atol=1e-12)
    assert back.model is model


def test_a_constrained_model_needs_the_reference_camera():
    assert CameraModel.FOCAL.needs_reference and CameraModel.FIXED.needs_reference
    assert not CameraModel.FREE.needs_reference and not CameraModel.ZERO_SKEW.needs_reference
    with pytest.raises(ValueError, match="reference"):
        Camera(ring_camera(0.0)[3], CameraModel.FOCAL).params()
    with pytest.raises(ValueError):
        CameraModel("affine")


def test_turned_180_maps_every_pixel_to_its_turned_position_and_back():
    K, R, t, P = ring_camera(10.0)
    size = (640, 480)
    cam = Camera(P)
    turned = cam.turned_180(size)
    X = np.random.default_rng(1).normal(scale=0.1, size=(30, 3))
    x, xt = cam.project(X), turned.project(X)
    np.testing.assert_allclose(xt, np.array(size) - 1 - x, atol=1e-9)
    np.testing.assert_allclose(turned.turned_180(size).P, P, atol=1e-12)
    np.testing.assert_allclose(turned.centre, cam.centre, atol=1e-12)
    np.testing.assert_allclose(cam.K_turned_180(size)[:2, 2], np.array(size) - 1 - K[:2, 2])


def test_the_model_is_its_name_in_configs_and_reports():
    import json
    assert CameraModel.FOCAL == "focal" and json.dumps(CameraModel.ZERO_SKEW) == '"zero-skew"'
    assert f"{CameraModel.FIXED}" == "fixed"
