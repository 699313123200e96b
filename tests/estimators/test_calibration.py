import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from stereoseed.estimators.calibration import (calibrate_camera, check_correspondences, dlt_projection,
                                    refine_projection, reprojection_rms)
from stereoseed.geometry.projection import camera_center, normalize_projection, project
from stereoseed.errors import StereoseedError
from geometry_helpers import box_points, ring_camera


def test_dlt_exact_data_recovers_P_to_1e8():
    rng = np.random.default_rng(0)
    K, R, t, P = ring_camera(35.0, f=780.0, skew=0.8, aspect=1.01, pp=(322.0, 236.0))
    X = box_points(rng, 60)
    P_est = dlt_projection(X, project(P, X))
    ref = normalize_projection(P)
    assert np.max(np.abs(P_est - ref)) / np.max(np.abs(ref)) < 1e-8


def test_refined_P_reaches_the_maximum_likelihood_optimum():
    rng = np.random.default_rng(1)
    K, R, t, P = ring_camera(0.0, f=780.0)
    X = box_points(rng, 150)
    ratios = []
    for sigma in (0.3, 1.0):
        for _ in range(5):
            x = project(P, X) + rng.normal(0, sigma, (len(X), 2))
            cal = calibrate_camera(X, x)
            # the global optimum, reached by refining from the true camera
            best = reprojection_rms(refine_projection(P, X, x), X, x)
            assert cal.rms_px <= best * 1.01
            # per-coordinate RMS against its expectation sigma * sqrt((2N - 11) / 2N)
            ratios.append(cal.rms_px / np.sqrt(2) / (sigma * np.sqrt((2 * len(X) - 11) / (2 * len(X)))))
    assert abs(np.mean(ratios) - 1.0) < 0.05


def test_center_error_scales_with_noise():
    rng = np.random.default_rng(2)
    K, R, t, P = ring_camera(0.0)
    X = box_points(rng, 120)
    C = camera_center(P)
    medians = []
    for sigma in (0.1, 1.0):
        errs = [np.linalg.norm(camera_center(calibrate_camera(X, project(P, X) + rng.normal(0, sigma, (120, 2))).P) - C)
                for _ in range(12)]
        medians.append(np.median(errs))
    assert 4.0 < medians[1] / medians[0] < 25.0  # ~10x for 10x the noise


def test_decomposition_matches_ground_truth():
    rng = np.random.default_rng(3)
    K, R, t, P = ring_camera(50.0, f=820.0, pp=(300.0, 250.0))
    X = box_points(rng, 80)
    cal = calibrate_camera(X, project(P, X))
    np.testing.assert_allclose(cal.K, K, rtol=1e-7, atol=1e-6)
    np.testing.assert_allclose(cal.R, R, atol=1e-9)
    np.testing.assert_allclose(cal.t, t, atol=1e-9)


@pytest.mark.parametrize("case, message", [
    ("few", "at least 6"),
    ("coplanar", "coplanar"),
    ("nan", "NaN"),
    ("length", "3D points but"),
])
def test_bad_inputs_are_refused_with_a_reason(case, message):
    rng = np.random.default_rng(4)
    X = box_points(rng, 20)
    x = project(ring_camera(0.0)[3], X)
    if case == "few":
        X, x = X[:5], x[:5]
    elif case == "coplanar":
        X = X.copy()
        X[:, 2] = 0.3
    elif case == "nan":
        x = x.copy()
        x[3, 1] = np.nan
    elif case == "length":
        x = x[:-1]
    with pytest.raises(StereoseedError, match=message):
        calibrate_camera(X, x)


def test_on_synthetic_box_calibration_points(box_scene):
    pattern, pts1, pts2 = box_scene.calibration_points()
    for i, pts in enumerate((pts1, pts2)):
        cal = calibrate_camera(pattern, pts)
        K_true = box_scene.K[i]
        assert np.max(np.abs(cal.K - K_true) / K_true[0, 0]) < 0.02
        assert np.linalg.norm(camera_center(cal.P) - camera_center(box_scene.P[i])) < 0.01  # 1 cm
        assert cal.rms_px < 3 * box_scene.config.calib_noise_px + 1e-6


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(allow_nan=True, allow_infinity=True, width=32),
                          st.floats(allow_nan=True, allow_infinity=True, width=32),
                          st.floats(allow_nan=True, allow_infinity=True, width=32)), max_size=12))
def test_random_inputs_either_calibrate_or_raise_clearly(rows):
    X = np.array(rows, dtype=float).reshape(-1, 3)
    x = X[:, :2] * 100.0 if len(X) else np.zeros((0, 2))
    try:
        check_correspondences(X, x)
    except StereoseedError as e:
        assert str(e)
        return
    try:
        with np.errstate(all="ignore"):
            cal = calibrate_camera(X, x)
    except StereoseedError as e:  # no camera could have seen these pixels: said in one line
        assert str(e).startswith("calibration: ") and "\n" not in str(e)
        return
    assert cal.P.shape == (3, 4) and np.all(np.isfinite(cal.P)) and cal.rms_px <= 5.0


@pytest.mark.parametrize("model", ["free", "zero-skew", "focal", "fixed"])
def test_refinement_reaches_scipys_least_squares_optimum(model):
    """The analytic-Jacobian LM finds the same optimum as SciPy's MINPACK LM (finite-difference
    Jacobian) on the same parameterisation: an oracle for the whole refinement."""
    from scipy.optimize import least_squares
    from stereoseed.geometry import models as camera_models

    rng = np.random.default_rng(7)
    K, R, t, P = ring_camera(20.0, f=780.0, skew=0.6, aspect=1.004, pp=(318.0, 243.0))
    X = box_points(rng, 80)
    x = project(P, X) + rng.normal(0, 0.7, (len(X), 2))
    ref_K = K.copy()
    ref_K[:2, :2] *= 0.9  # a reference 10 % less zoomed: the focal model must find the zoom
    start = camera_models.project_to_model(P, model, ref_K)
    params, fixed = camera_models.params_from_projection(start, model, ref_K)
    params[-6:-3] += 0.01  # off by ~0.6 deg
    params[-3:] += 0.02  # and 2 cm
    start = camera_models.projection_from_params(params, model, fixed)

    def residuals(p):
        return (project(camera_models.projection_from_params(p, model, fixed), X) - x).ravel()

    oracle = least_squares(residuals, params, method="lm", xtol=1e-12, ftol=1e-12)
    P_oracle = camera_models.projection_from_params(oracle.x, model, fixed)
    P_ours = refine_projection(start, X, x, model=model, reference_K=ref_K)
    assert reprojection_rms(P_ours, X, x) <= reprojection_rms(P_oracle, X, x) * (1 + 1e-9)
    assert np.linalg.norm(camera_center(P_ours) - camera_center(P_oracle)) < 1e-6  # metres
    assert reprojection_rms(P_ours, X, x) < reprojection_rms(start, X, x) / 5


def test_huber_refinement_ignores_gross_outliers():
    rng = np.random.default_rng(8)
    K, R, t, P = ring_camera(-30.0, f=800.0)
    X = box_points(rng, 100)
    x = project(P, X) + rng.normal(0, 0.3, (len(X), 2))
    x[:15] += rng.uniform(20, 60, (15, 2))  # 15 % gross mismatches
    start = dlt_projection(X[15:], x[15:])
    robust = refine_projection(start, X, x, loss="huber", f_scale=1.0)
    plain = refine_projection(start, X, x)
    err = lambda Pc: np.linalg.norm(camera_center(Pc) - camera_center(P))
    clean = refine_projection(start, X[15:], x[15:])  # the fit without the mismatches
    assert err(robust) < 2 * max(err(clean), 1e-3)
    assert err(plain) > 10 * err(clean)  # the mismatches do matter to least squares


def test_refinement_of_a_point_on_the_cameras_plane_does_not_raise():
    """A point at depth 0 projects to infinity: the cost is infinite, as in NumPy, and the start
    comes back (the compiled loop follows NumPy's arithmetic, not Python's ZeroDivisionError)."""
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    P = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 5.0], [0.0, 1.0, 6.0], [1.0, 1.0, 7.0], [-1.0, 0.5, 4.0],
                  [0.5, -1.0, 5.0], [0.2, 0.3, 8.0]])  # the first point at the camera centre's depth
    x = np.tile([433.0, 189.0], (len(X), 1))
    for model, ref in (("free", None), ("focal", K)):
        out = refine_projection(P, X, x, model=model, reference_K=ref, loss="huber")
        assert out.shape == (3, 4)
