import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from stereoseed.geometry.projection import (camera_center, decompose_projection, depths, epipolar_distances,
                               fundamental_from_projections, normalize_projection, project)
from geometry_helpers import box_points, ring_camera


def test_pixel_convention_principal_point():
    # A point on the optical axis lands exactly on the principal point (cx, cy): pixel (0, 0) is
    # the centre of the top-left pixel, so no half-pixel offset enters P.
    K, R, t, P = ring_camera(30.0, pp=(319.5, 239.5))
    C = camera_center(P)
    on_axis = C + 0.7 * R[2]
    np.testing.assert_allclose(project(P, on_axis[None])[0], [319.5, 239.5], atol=1e-9)
    # y grows downwards: a point above the target projects to a smaller v
    up = project(P, np.array([[0.0, 0.0, 0.4], [0.0, 0.0, 0.0]]))
    assert up[0, 1] < up[1, 1]


def test_decomposition_recovers_krt_whatever_the_scale_and_sign():
    K, R, t, P = ring_camera(75.0, f=900.0, skew=1.5, aspect=1.02, pp=(310.0, 250.0))
    for s in (1.0, -2.5, 1e-4):
        K2, R2, t2 = decompose_projection(s * P)
        np.testing.assert_allclose(K2, K, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)
        assert np.linalg.det(R2) == pytest.approx(1.0)
        assert np.all(np.diag(K2) > 0)


def test_center_and_depths():
    rng = np.random.default_rng(1)
    K, R, t, P = ring_camera(10.0)
    np.testing.assert_allclose(camera_center(P), -R.T @ t, atol=1e-12)
    X = box_points(rng, 20)
    d = depths(-7.0 * P, X)
    np.testing.assert_allclose(d, (X @ R.T + t)[:, 2], rtol=1e-10)
    assert np.all(d > 0)


def test_fundamental_matrix_vanishes_on_true_matches():
    rng = np.random.default_rng(2)
    P1 = ring_camera(0.0)[3]
    P2 = ring_camera(20.0, f=850.0)[3]
    X = box_points(rng, 50)
    x1, x2 = project(P1, X), project(P2, X)
    F = fundamental_from_projections(P1, P2)
    assert np.max(epipolar_distances(F, x1, x2)) < 1e-8
    # shifting x2 by 3 px perpendicular to its epipolar line gives a 3 px distance
    l2 = np.hstack([x1, np.ones((50, 1))]) @ F.T
    n = l2[:, :2] / np.linalg.norm(l2[:, :2], axis=1, keepdims=True)
    np.testing.assert_allclose(epipolar_distances(F, x1, x2 + 3.0 * n).min(), 3.0, rtol=0.05)


@settings(max_examples=50, deadline=None)
@given(angle=st.floats(0, 360), f=st.floats(200, 5000), skew=st.floats(-5, 5),
       aspect=st.floats(0.8, 1.25), scale=st.floats(-1e3, 1e3).filter(lambda s: abs(s) > 1e-6))
def test_decompose_roundtrip_property(angle, f, skew, aspect, scale):
    K, R, t, P = ring_camera(angle, f=f, skew=skew, aspect=aspect)
    K2, R2, t2 = decompose_projection(scale * P)
    np.testing.assert_allclose(K2, K, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(R2, R, atol=1e-9)
    np.testing.assert_allclose(normalize_projection(scale * P), normalize_projection(P), atol=1e-9)


@pytest.mark.parametrize("model", ["free", "zero-skew", "focal", "fixed"])
def test_projection_derivatives_match_central_differences(model):
    from stereoseed.geometry import models as camera_models

    rng = np.random.default_rng(3)
    ref = np.array([[800.0, 0.5, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]])
    K = ref.copy()
    K[:2, :2] *= 1.1
    K = camera_models.K_from_intrinsics(camera_models._intrinsics_from_K(K, model, ref), model, ref)
    R = camera_models.rotation_from_vector(rng.normal(size=3))
    t = rng.normal(size=3)
    analytic = camera_models.projection_derivatives(K, R, t, model, ref)
    intrinsics = camera_models._intrinsics_from_K(K, model, ref)
    ni = len(intrinsics)

    def P_of(p):  # the parameterisation the derivatives are of: left rotation increment
        K_p = camera_models.K_from_intrinsics(p[:ni], model, ref)
        return K_p @ np.hstack([camera_models.rotation_from_vector(p[ni:ni + 3]) @ R, (t + p[ni + 3:]).reshape(3, 1)])

    p0 = np.r_[intrinsics, np.zeros(6)]
    for j in range(len(p0)):
        e = np.zeros(len(p0))
        e[j] = 1e-6 * max(1.0, abs(p0[j]))
        numeric = (P_of(p0 + e) - P_of(p0 - e)) / (2 * e[j])
        assert np.abs(numeric - analytic[j]).max() < 1e-6 * max(1.0, np.abs(analytic[j]).max())


@pytest.mark.parametrize("model", ["free", "zero-skew", "focal", "fixed"])
def test_projections_from_params_are_the_ones_of_each_camera(model):
    # the batched form the BA uses gives each camera exactly as the one-camera form does,
    # a rotation below the first-order threshold included
    from stereoseed.geometry import models as camera_models

    rng = np.random.default_rng(4)
    n, ni = camera_models.n_params(model), camera_models.N_INTRINSICS[model]
    params = rng.normal(size=(6, n))
    params[:, :ni] = 400.0 + 100.0 * np.abs(params[:, :ni])
    params[0, ni:ni + 3], params[1, ni:ni + 3] = 0.0, 1e-14
    refs = np.stack([np.array([[800.0 + i, 0.5, 320.0], [0.0, 790.0, 240.0 + i], [0.0, 0.0, 1.0]]) for i in range(6)])
    one_by_one = np.stack([camera_models.projection_from_params(p, model, r) for p, r in zip(params, refs)])
    np.testing.assert_array_equal(camera_models.projections_from_params(params, model, refs), one_by_one)
    shared = np.stack([camera_models.projection_from_params(p, model, refs[0]) for p in params])
    np.testing.assert_array_equal(camera_models.projections_from_params(params, model, refs[0]), shared)


def test_quaternions_and_rotation_vectors_are_scipys_at_every_angle():
    """camera_models' rotation conversions against scipy's Rotation (the oracle): random
    rotations, tiny angles and half turns (where an inverse cosine would lose half the digits)."""
    from scipy.spatial.transform import Rotation

    from stereoseed.geometry import models as camera_models

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rotations = [Rotation.random(random_state=i) for i in range(300)]
    rotations += [Rotation.from_rotvec(axis * a) for a in (0.0, 1e-13, 1e-6, np.pi - 1e-9, np.pi)]
    rotations += [Rotation.from_matrix(np.diag(d)) for d in ([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])]
    for rot in rotations:
        R = rot.as_matrix()
        q = camera_models.quaternion_from_rotation(R)
        x, y, z, w = rot.as_quat()
        want = np.array([w, x, y, z])
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-15
        assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-14  # q and -q: the same rotation
        np.testing.assert_allclose(camera_models.rotation_from_quaternion(q), R, atol=1e-14)
        rvec = camera_models.rotation_vector(R)
        assert np.linalg.norm(rvec) <= np.pi + 1e-12
        np.testing.assert_allclose(camera_models.rotation_from_vector(rvec), R, atol=1e-14)
        if np.linalg.norm(rvec) < np.pi - 1e-6:  # a half turn's vector is +-(axis pi)
            np.testing.assert_allclose(rvec, rot.as_rotvec(), atol=1e-14)
    np.testing.assert_allclose(camera_models.rotation_from_quaternion([2.0, 0, 0, 0]), np.eye(3))  # normalised first
    for bad in ([0.0, 0, 0, 0], [np.nan, 1, 0, 0]):
        with pytest.raises(ValueError):
            camera_models.rotation_from_quaternion(bad)
