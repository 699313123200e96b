"""The rig's bundle adjustment: stations of a held rig, against known walks and scipy as oracle."""
import numpy as np
import pytest
from geometry_helpers import box_points, make_rig, relative_pose, ring_camera
from scipy.optimize import least_squares

from stereoseed.estimators.rig_bundle import (
    RigBundleConfig,
    RigBundleProblem,
    rig_bundle_adjust,
    rig_observation_errors,
    station_projections,
)
from stereoseed.estimators.rig_resection import Rig
from stereoseed.estimators.robust import huber_cost_of_norms
from stereoseed.geometry.models import rotation_from_vector, rotation_vector
from stereoseed.geometry.projection import decompose_projection, project


def walk(rig, rng, n_stations=5, n_points=200, noise=0.0, step=25.0):
    """Stations round the box (R (N, 3, 3), t (N, 3)), points and each camera's observations of
    80 % of them: (R, t, X, obs_station, obs_side, obs_point, obs_xy)."""
    poses = [ring_camera(30.0 + step * k)[1:3] for k in range(n_stations)]
    R, t = np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
    X = box_points(rng, n_points)
    Ps = station_projections(rig, R, t)
    st, sd, pt, xy = [], [], [], []
    for k in range(n_stations):
        for s in (0, 1):
            seen = np.flatnonzero(rng.random(n_points) < 0.8)
            st.append(np.full(len(seen), k))
            sd.append(np.full(len(seen), s))
            pt.append(seen)
            xy.append(project(Ps[k, s], X[seen]) + rng.normal(0.0, noise, (len(seen), 2)))
    return R, t, X, *map(np.concatenate, (st, sd, pt, xy))


def perturbed(rng, R, t, X, angle=0.01, shift=0.01, point_shift=0.005):
    """Every station but the first turned by ~angle rad and moved by ~shift, the points moved."""
    R0 = np.array([rotation_from_vector(rng.normal(0.0, angle, 3)) @ r if k else r for k, r in enumerate(R)])
    t0 = t + rng.normal(0.0, shift, t.shape) * (np.arange(len(t)) > 0)[:, None]
    return R0, t0, X + rng.normal(0.0, point_shift, X.shape)


def test_a_perturbed_walk_goes_back_to_the_truth_with_the_rig_held():
    rig = make_rig()
    rng = np.random.default_rng(0)
    R, t, X, *obs = walk(rig, rng)
    R0, t0, X0 = perturbed(rng, R, t, X)
    res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X0, *obs))
    assert res.rms_before > 3.0 and res.rms_after < 1e-8
    np.testing.assert_allclose(res.R, R, atol=1e-10)
    np.testing.assert_allclose(res.t, t, atol=1e-10)
    np.testing.assert_allclose(res.points, X, atol=1e-10)
    np.testing.assert_array_equal(res.R[0], R0[0])  # the gauge: the first station does not move
    np.testing.assert_array_equal(res.t[0], t0[0])
    assert res.rig is rig
    for P_left, P_right in res.projections():  # every station keeps the rig's relative pose
        R_rl, t_rl = relative_pose(P_left, P_right)
        np.testing.assert_allclose(R_rl, rig.R_rl, atol=1e-9)
        np.testing.assert_allclose(t_rl, rig.t_rl, atol=1e-9)


def test_noisy_walk_least_squares_agrees_with_scipy_on_free_poses():
    """The held-rig optimum by least squares, against scipy's own solver (finite differences,
    each station's absolute rotation vector, dense): the same minimum."""
    rig = make_rig()
    rng = np.random.default_rng(1)
    R, t, X, st, sd, pt, xy = walk(rig, rng, n_stations=3, n_points=40, noise=1.0)
    R0, t0, X0 = perturbed(rng, R, t, X, angle=0.003, shift=0.003, point_shift=0.002)
    res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X0, st, sd, pt, xy), RigBundleConfig(huber_px=np.inf, min_improvement=1e-14))
    assert res.rms_after < res.rms_before

    def residuals(p):
        Rs = np.concatenate([R0[:1], [rotation_from_vector(v) for v in p[:6].reshape(2, 3)]])
        ts = np.concatenate([t0[:1], p[6:12].reshape(2, 3)])
        P = station_projections(rig, Rs, ts)[st, sd]  # (O, 3, 4)
        h = np.einsum("oij,oj->oi", P[:, :, :3], p[12:].reshape(-1, 3)[pt]) + P[:, :, 3]
        return (h[:, :2] / h[:, 2:] - xy).ravel()

    p0 = np.concatenate([np.ravel([rotation_vector(r) for r in R0[1:]]), t0[1:].ravel(), X0.ravel()])
    oracle = least_squares(residuals, p0, method="lm", xtol=1e-14, ftol=1e-14).x
    np.testing.assert_allclose(res.t[1:].ravel(), oracle[6:12], atol=1e-7)
    np.testing.assert_allclose(np.ravel([rotation_vector(r) for r in res.R[1:]]), oracle[:6], atol=1e-8)
    np.testing.assert_allclose(res.points.ravel(), oracle[12:], atol=1e-7)


def test_a_refined_rig_finds_the_true_relative_pose_and_keeps_the_baseline():
    truth = make_rig()
    rng = np.random.default_rng(2)
    R, t, X, *obs = walk(truth, rng)
    off_R = rotation_from_vector(np.radians([0.3, -0.5, 0.2])) @ truth.R_rl
    off_t = rotation_from_vector(np.radians([0.0, 2.0, 1.0])) @ truth.t_rl  # direction 2 degrees off
    wrong = Rig(truth.K_left, truth.K_right, off_R, off_t)
    R0, t0, X0 = perturbed(rng, R, t, X)
    held = rig_bundle_adjust(RigBundleProblem(wrong, R0, t0, X0, *obs))
    refined = rig_bundle_adjust(RigBundleProblem(wrong, R0, t0, X0, *obs, refine_rig=True))
    assert held.rms_after > 1.0  # the wrong rig cannot explain the images
    assert refined.rms_after < 1e-8
    np.testing.assert_allclose(refined.rig.R_rl, truth.R_rl, atol=1e-10)
    np.testing.assert_allclose(refined.rig.t_rl, truth.t_rl, atol=1e-10)
    assert refined.rig.baseline == pytest.approx(truth.baseline, abs=1e-15)
    for P_left, P_right in refined.projections():
        R_rl, t_rl = relative_pose(P_left, P_right)
        np.testing.assert_allclose(R_rl, refined.rig.R_rl, atol=1e-9)
        np.testing.assert_allclose(t_rl, refined.rig.t_rl, atol=1e-9)


def test_huber_loss_on_each_error_norm_resists_gross_outliers():
    rig = make_rig()
    rng = np.random.default_rng(3)
    R, t, X, st, sd, pt, xy = walk(rig, rng, noise=0.5)
    bad = rng.random(len(xy)) < 0.05
    xy = xy.copy()
    xy[bad] += rng.uniform(20.0, 60.0, (int(bad.sum()), 2)) * rng.choice([-1, 1], (int(bad.sum()), 2))
    R0, t0, X0 = perturbed(rng, R, t, X)
    errors = {}
    for delta in (1.0, np.inf):
        res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X0, st, sd, pt, xy), RigBundleConfig(huber_px=delta))
        assert res.rms_after < res.rms_before
        errors[delta] = max(np.linalg.norm(-r.T @ tt - (-R[k].T @ t[k])) for k, (r, tt) in enumerate(zip(res.R, res.t)))
        good = rig_observation_errors(rig, res.R, res.t, res.points, st, sd, pt, xy)[~bad]
        errors[delta, "good"] = np.sqrt(np.mean(good ** 2))
    assert errors[1.0] < 0.3 * errors[np.inf]
    assert errors[1.0, "good"] < 0.8  # the good observations (0.5 px per axis) stay near their noise


def test_the_robust_result_is_a_minimum_of_the_huber_cost_of_each_norm():
    """The gradient of the house's Huber cost (robust.py, on each observation's 2D error) over
    every free unknown, by central differences: nil at the result."""
    rig = make_rig()
    rng = np.random.default_rng(7)
    R, t, X, st, sd, pt, xy = walk(rig, rng, n_stations=3, n_points=30, noise=1.0)
    xy = xy + (rng.random(len(xy)) < 0.1)[:, None] * rng.uniform(-30.0, 30.0, xy.shape)
    R0, t0, X0 = perturbed(rng, R, t, X, angle=0.003, shift=0.003, point_shift=0.002)
    res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X0, st, sd, pt, xy), RigBundleConfig(min_improvement=1e-15, max_iterations=500))

    def gradient(Rs, ts, pts):
        def cost(p):
            Rp = np.concatenate([Rs[:1], [rotation_from_vector(v) @ r for v, r in zip(p[:6].reshape(2, 3), Rs[1:])]])
            tp = np.concatenate([ts[:1], ts[1:] + p[6:12].reshape(2, 3)])
            return huber_cost_of_norms(rig_observation_errors(rig, Rp, tp, pts + p[12:].reshape(-1, 3), st, sd, pt, xy), 1.0)

        n = 12 + pts.size
        return np.array([(cost(e * 1e-6) - cost(-e * 1e-6)) / 2e-6 for e in np.eye(n)])

    start, end = gradient(R0, t0, X0), gradient(res.R, res.t, res.points)
    assert np.abs(end).max() < 1e-6 * np.abs(start).max()  # reweighting converges linearly: 200 iterations


def test_the_gauge_must_be_fixed():
    rig = make_rig()
    R, t, X, *obs = walk(rig, np.random.default_rng(5), n_stations=2, n_points=20)
    with pytest.raises(ValueError, match="gauge"):
        rig_bundle_adjust(RigBundleProblem(rig, R, t, X, *obs, free_stations=np.ones(2, bool)))
    # fixed points fix it too: every station free, the points held
    R0, t0, _ = perturbed(np.random.default_rng(6), R, t, X)
    R0[0] = rotation_from_vector([0.01, 0.0, 0.0]) @ R[0]
    res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X, *obs, free_stations=np.ones(2, bool),
                                             free_points=np.zeros(len(X), bool)))
    np.testing.assert_allclose(res.R, R, atol=1e-10)
    np.testing.assert_array_equal(res.points, X)
    assert decompose_projection(res.projections()[0, 1])[0] == pytest.approx(rig.K_right, abs=1e-9)


def test_the_rms_counts_every_observation_fixed_ones_too():
    rig = make_rig()
    rng = np.random.default_rng(8)
    R, t, X, st, sd, pt, xy = walk(rig, rng, n_stations=3, n_points=60, noise=1.0)
    free_points = np.arange(len(X)) % 2 == 0  # the first station's views of the others touch nothing free
    R0, t0, X0 = perturbed(rng, R, t, X)
    res = rig_bundle_adjust(RigBundleProblem(rig, R0, t0, X0, st, sd, pt, xy, free_points=free_points))
    np.testing.assert_array_equal(res.points[~free_points], X0[~free_points])
    for rms, (R_, t_, X_) in ((res.rms_before, (R0, t0, X0)), (res.rms_after, (res.R, res.t, res.points))):
        every = rig_observation_errors(rig, R_, t_, X_, st, sd, pt, xy)
        assert rms == pytest.approx(np.sqrt(np.mean(every ** 2)), rel=1e-12)
    assert res.rms_after < 0.5 * res.rms_before
