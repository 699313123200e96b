"""The generalised resection of a stereo rig's station, against stations of known pose."""
import numpy as np
import pytest
from geometry_helpers import box_points, make_rig, relative_pose, ring_camera

from stereoseed.errors import StereoseedError
from stereoseed.estimators.resection import resect
from stereoseed.estimators.rig_resection import Rig, RigResectionConfig, resect_rig
from stereoseed.geometry.models import rotation_from_vector, rotation_vector
from stereoseed.geometry.projection import decompose_projection, project

SIZE = (640, 480)
CHI2_6_9999 = 27.86  # the 99.99 % quantile of chi-square with 6 degrees of freedom


def station_pairs(rig, angle, rng, n_left, n_right, noise=0.0, outliers=0.0):
    """A station at ``angle`` on the ring: (R, t), and 2D-3D pairs of box points inside each
    camera's image (n_left, n_right of them), with Gaussian pixel noise and a share of outliers
    moved 10-80 px. Returns R, t, X, x, side, bad."""
    _, R, t, _ = ring_camera(angle)
    Ps = rig.projections(R, t)
    X, x, side = [], [], []
    for s, n in ((0, n_left), (1, n_right)):
        pts = box_points(rng, 20 * n + 50)
        uv = project(Ps[s], pts)
        inside = np.all((uv > 5) & (uv < np.array(SIZE) - 5), axis=1)
        X.append(pts[inside][:n])
        x.append(uv[inside][:n])
        side.append(np.full(n, s))
    X, x, side = np.concatenate(X), np.concatenate(x), np.concatenate(side)
    x = x + rng.normal(0.0, noise, x.shape)
    bad = rng.random(len(X)) < outliers
    direction = rng.normal(size=(int(bad.sum()), 2))
    x[bad] += direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(10, 80, (int(bad.sum()), 1))
    return R, t, X, x, side, bad


def pose_chi2(rig, R, t, R_est, t_est, X, side, sigma):
    """(delta)^T J^T J (delta) / sigma^2 of the estimate's pose error (rotation increment, t) at
    the truth, over the pairs (X, side): how many standard errors the estimate is off."""
    def pixels(p):
        Ps = rig.projections(rotation_from_vector(p[:3]) @ R, t + p[3:])
        return np.where(side[:, None] == 0, project(Ps[0], X), project(Ps[1], X)).ravel()

    J = np.stack([(pixels(e * 1e-7) - pixels(-e * 1e-7)) / 2e-7 for e in np.eye(6)], axis=1)
    delta = np.concatenate([rotation_vector(R_est @ R.T), t_est - t])
    return float(delta @ (J.T @ J) @ delta) / sigma ** 2


def test_exact_pairs_give_the_station_pose():
    rig = make_rig()
    rng = np.random.default_rng(0)
    for angle in (10.0, 75.0, 140.0):
        R, t, X, x, side, _ = station_pairs(rig, angle, rng, 40, 40)
        res = resect_rig(rig, X, x, side)
        assert res.success and res.reason is None
        assert res.n_inliers == (40, 40) and res.inliers.all()
        np.testing.assert_allclose(res.R, R, atol=1e-6)
        np.testing.assert_allclose(res.t, t, atol=1e-6)
        assert res.rms_px < 1e-6


def test_noisy_pairs_with_30_percent_outliers_give_the_pose_within_the_noise():
    rig = make_rig()
    rng = np.random.default_rng(1)
    R, t, X, x, side, bad = station_pairs(rig, 50.0, rng, 150, 150, noise=1.0, outliers=0.3)
    res = resect_rig(rig, X, x, side)
    assert res.success
    assert not np.any(res.inliers & bad)  # every outlier is at least 10 px off: none kept
    assert res.inliers[~bad].mean() > 0.8  # 2D noise of 1 px per axis: 86 % lie within 2 px
    assert min(res.n_inliers) > 80  # both cameras count
    assert pose_chi2(rig, R, t, res.R, res.t, X[~bad], side[~bad], 1.0) < CHI2_6_9999
    assert 0.9 < res.rms_px < 1.4


@pytest.mark.parametrize("noise, outliers", [(0.0, 0.0), (1.0, 0.3)])
def test_a_station_only_the_right_camera_sees_well_is_placed(noise, outliers):
    rig = make_rig()
    rng = np.random.default_rng(2)
    R, t, X, x, side, bad = station_pairs(rig, 100.0, rng, 4, 60, noise=noise, outliers=outliers)
    left = side == 0
    with pytest.raises(StereoseedError):  # the left camera alone: too few pairs for any resection
        resect(X[left], x[left])
    res = resect_rig(rig, X, x, side)
    assert res.success and res.n_inliers[1] >= 35
    if noise == 0:
        np.testing.assert_allclose(res.R, R, atol=1e-6)
        np.testing.assert_allclose(res.t, t, atol=1e-6)
    else:
        assert not np.any(res.inliers & bad)
        assert pose_chi2(rig, R, t, res.R, res.t, X[~bad], side[~bad], noise) < CHI2_6_9999


def test_two_weak_cameras_make_one_station():
    rig = make_rig()
    rng = np.random.default_rng(3)
    R, t, X, x, side, _ = station_pairs(rig, 30.0, rng, 8, 8, noise=0.3)
    for s in (0, 1):  # 8 pairs each: below a single image's 12 inliers
        with pytest.raises(StereoseedError, match="agree"):
            resect(X[side == s], x[side == s])
    res = resect_rig(rig, X, x, side)
    assert res.success and res.n_inliers == (8, 8)
    assert pose_chi2(rig, R, t, res.R, res.t, X, side, 0.3) < CHI2_6_9999


def test_the_station_cameras_have_the_rig_relative_pose_exactly():
    rig = make_rig(baseline=0.3, toe_in_deg=12.0, focal_ratio=0.9)
    rng = np.random.default_rng(4)
    _, _, X, x, side, _ = station_pairs(rig, 200.0, rng, 30, 30, noise=1.0, outliers=0.2)
    res = resect_rig(rig, X, x, side)
    P_left, P_right = res.projections()
    R_rl, t_rl = relative_pose(P_left, P_right)
    np.testing.assert_allclose(R_rl, rig.R_rl, atol=1e-9)
    np.testing.assert_allclose(t_rl, rig.t_rl, atol=1e-9)
    np.testing.assert_allclose(decompose_projection(P_left)[0], rig.K_left, atol=1e-9 * 800)
    np.testing.assert_allclose(decompose_projection(P_right)[0], rig.K_right, atol=1e-9 * 800)


def test_rig_from_a_calibrated_pair_and_back():
    rig = make_rig()
    _, R, t, _ = ring_camera(40.0)
    again = Rig.from_projections(*rig.projections(R, t))
    for a, b in ((again.K_left, rig.K_left), (again.K_right, rig.K_right)):
        np.testing.assert_allclose(a, b, atol=1e-9 * 800)
    np.testing.assert_allclose(again.R_rl, rig.R_rl, atol=1e-12)
    np.testing.assert_allclose(again.t_rl, rig.t_rl, atol=1e-12)
    assert abs(again.baseline - 0.12) < 1e-12
    R_back, t_back = rig.left_pose(1, *rig.right_pose(R, t))
    np.testing.assert_allclose(R_back, R, atol=1e-15)
    np.testing.assert_allclose(t_back, t, atol=1e-15)


def test_failures_are_values_with_a_reason_and_bad_input_is_refused():
    rig = make_rig()
    rng = np.random.default_rng(5)
    _, _, X, x, side, _ = station_pairs(rig, 0.0, rng, 30, 30)
    res = resect_rig(rig, X, rng.uniform(0, 640, x.shape), side)
    assert not res.success and "agree" in res.reason and res.n_hypotheses == RigResectionConfig().ransac_max_iters
    few = resect_rig(rig, X[:10], x[:10], side[:10])
    assert not few.success and "at least 12" in few.reason and few.R is None
    with pytest.raises(ValueError, match="no station pose"):
        few.projections()
    two_each = np.r_[0, 0, 1, 1] == 1
    assert "minimal sample" in resect_rig(rig, X[:4], x[:4], two_each, RigResectionConfig(min_inliers=3)).reason
    with pytest.raises(StereoseedError, match="side"):
        resect_rig(rig, X, x, np.full(len(X), 2))
    with pytest.raises(StereoseedError, match="pixels"):
        resect_rig(rig, X, x[:-1], side)
    with pytest.raises(StereoseedError, match="R_rl"):
        Rig(rig.K_left, rig.K_right, 2 * np.eye(3), rig.t_rl)
    with pytest.raises(StereoseedError, match="K_right"):
        Rig(rig.K_left, rig.K_right.T, rig.R_rl, rig.t_rl)
    np.testing.assert_array_equal(Rig(2 * rig.K_left, rig.K_right, rig.R_rl, rig.t_rl).K_left, rig.K_left)
    with pytest.raises(ValueError, match="min_inliers"):
        RigResectionConfig(min_inliers=2)
