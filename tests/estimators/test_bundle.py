import numpy as np
import pytest
from scipy.optimize import least_squares

from stereoseed.geometry import models as camera_models
from stereoseed.estimators.bundle import BundleProblem, bundle_adjust
from stereoseed.geometry.projection import camera_center, project
from stereoseed.config import BundleConfig
from geometry_helpers import box_points, ring_camera


def _scene(rng, n_cams=5, n_pts=300, noise=0.0):
    Ps = np.stack([ring_camera(20.0 * i, f=800 + 15 * i)[3] for i in range(n_cams)])
    X = box_points(rng, n_pts)
    oc, op, xy = [], [], []
    for c in range(n_cams):
        seen = rng.random(n_pts) < 0.8
        oc.append(np.full(seen.sum(), c))
        op.append(np.flatnonzero(seen))
        xy.append(project(Ps[c], X[seen]) + rng.normal(0, noise, (seen.sum(), 2)))
    return Ps, X, np.concatenate(oc), np.concatenate(op), np.concatenate(xy)


def _perturb(rng, P, model, scale):
    p, ref = camera_models.params_from_projection(P, model, None)
    p = p + rng.normal(0, scale, p.shape) * np.maximum(np.abs(p), 0.05) * 0.01
    return camera_models.projection_from_params(p, model, ref)


def test_recovers_exact_solution_from_perturbed_start():
    rng = np.random.default_rng(0)
    Ps, X, oc, op, xy = _scene(rng)
    free_c = np.array([False, False, True, True, True])
    P0 = Ps.copy()
    for c in np.flatnonzero(free_c):
        P0[c] = _perturb(rng, Ps[c], "free", 1.0)
    X0 = X + rng.normal(0, 0.005, X.shape)
    res = bundle_adjust(BundleProblem(P0, free_c, X0, np.ones(len(X), bool), oc, op, xy),
                        BundleConfig(max_iterations=50))
    assert res.rms_before > 1.0
    assert res.rms_after < 1e-6
    for c in np.flatnonzero(free_c):
        assert np.linalg.norm(camera_center(res.Ps[c]) - camera_center(Ps[c])) < 1e-7
    seen_twice = np.bincount(op, minlength=len(X)) >= 2
    assert np.max(np.abs(res.points - X)[seen_twice]) < 1e-7
    np.testing.assert_array_equal(res.Ps[:2], Ps[:2])


def test_matches_scipy_least_squares_on_noisy_data():
    rng = np.random.default_rng(1)
    Ps, X, oc, op, xy = _scene(rng, n_cams=4, n_pts=120, noise=0.5)
    free_c = np.array([False, False, True, True])
    res = bundle_adjust(BundleProblem(Ps, free_c, X, np.ones(len(X), bool), oc, op, xy),
                        BundleConfig(huber_px=1e9, max_iterations=100))
    # reference: scipy's trust-region least squares over the same parameters
    p0 = np.concatenate([camera_models.params_from_projection(Ps[c], "free")[0] for c in (2, 3)] + [X.ravel()])

    def fun(p):
        P_all = Ps.copy()
        P_all[2] = camera_models.projection_from_params(p[:11], "free")
        P_all[3] = camera_models.projection_from_params(p[11:22], "free")
        Xp = p[22:].reshape(-1, 3)
        h = np.einsum("oij,oj->oi", P_all[oc][:, :, :3], Xp[op]) + P_all[oc][:, :, 3]
        return (h[:, :2] / h[:, 2:3] - xy).ravel()

    ref = least_squares(fun, p0, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12)
    ref_rms = np.sqrt(2 * ref.cost / len(oc))
    assert res.rms_after == pytest.approx(ref_rms, rel=1e-3)


def test_fixed_points_pin_a_free_camera():
    # The paper.md trap: the new camera with only the new points free drifts; with the old
    # (fixed) points' observations in the cost it cannot.
    rng = np.random.default_rng(2)
    Ps, X, oc, op, xy = _scene(rng, n_cams=3, n_pts=200)
    free_c = np.array([False, False, True])
    free_p = np.zeros(len(X), bool)
    free_p[100:] = True
    P0 = Ps.copy()
    P0[2] = _perturb(rng, Ps[2], "free", 1.0)
    X0 = X.copy()
    X0[100:] += rng.normal(0, 0.003, (100, 3))
    res = bundle_adjust(BundleProblem(P0, free_c, X0, free_p, oc, op, xy), BundleConfig(max_iterations=50))
    assert np.linalg.norm(camera_center(res.Ps[2]) - camera_center(Ps[2])) < 1e-6
    np.testing.assert_array_equal(res.points[:100], X[:100])


@pytest.mark.parametrize("model", ["zero-skew", "focal"])
def test_constrained_models(model):
    rng = np.random.default_rng(3)
    Ps, X, oc, op, xy = _scene(rng, n_cams=4, n_pts=200)
    ref_K = camera_models.krt_from_params(camera_models.params_from_projection(Ps[1], "free")[0], "free")[0]
    free_c = np.array([False, False, True, True])
    P0 = Ps.copy()
    for c in (2, 3):
        P0[c] = _perturb(rng, Ps[c], model if model != "focal" else "zero-skew", 0.5)
    res = bundle_adjust(BundleProblem(P0, free_c, X, np.ones(len(X), bool), oc, op, xy, model=model,
                                      reference_K=ref_K), BundleConfig(max_iterations=50))
    assert res.rms_after < 1e-5


def _reduced_camera_case():
    """A random reduced camera system and its dense reference -W V^-1 W^T (a camera may see a
    point twice)."""
    rng = np.random.default_rng(3)
    n_cams, n_points, n = 4, 30, 7
    cams = rng.integers(0, n_cams, 150)
    points = rng.integers(0, n_points, 150)
    W = rng.normal(size=(150, n, 3))
    V = rng.normal(size=(n_points, 3, 3))
    V = V @ np.swapaxes(V, 1, 2) + np.eye(3)  # symmetric positive definite
    Vinv = np.linalg.inv(V)
    dense_W = np.zeros((n_cams * n, n_points * 3))
    for o in range(150):  # a camera seeing a point twice adds its blocks
        dense_W[cams[o] * n:(cams[o] + 1) * n, points[o] * 3:(points[o] + 1) * 3] += W[o]
    dense_Vinv = np.zeros((n_points * 3, n_points * 3))
    for p in range(n_points):
        dense_Vinv[p * 3:(p + 1) * 3, p * 3:(p + 1) * 3] = Vinv[p]
    order = np.lexsort((cams, points))  # by point, then by camera
    starts = np.searchsorted(points[order], np.arange(n_points + 1))
    Wt = np.swapaxes(W, 1, 2).copy()
    return (order, starts, cams, Wt, W @ Vinv[points], n_cams), -dense_W @ dense_Vinv @ dense_W.T


def test_reduced_camera_matrix_is_w_vinv_wt():
    from stereoseed.estimators._schur import reduced_camera_matrix, thread_rows

    args, expected = _reduced_camera_case()
    order, starts, cams, _, _, n_cams = args
    rows = thread_rows(order, starts, cams, n_cams)
    np.testing.assert_allclose(reduced_camera_matrix(*args, rows), expected, atol=1e-9)


def test_reduced_camera_matrix_shared_among_threads_is_the_same(monkeypatch):
    # each thread owns whole block rows: the same additions in the same order, bit for bit
    from stereoseed.estimators import _schur as bundle

    args, _ = _reduced_camera_case()
    order, starts, cams, _, _, n_cams = args
    single = bundle.reduced_camera_matrix(*args, bundle.thread_rows(order, starts, cams, n_cams))
    from stereoseed import threads

    monkeypatch.setattr(threads, "_chunks", 3)
    monkeypatch.setattr(bundle, "PAIRS_PER_THREAD", 1)
    rows = bundle.thread_rows(order, starts, cams, n_cams)
    assert len(rows) == 4  # three threads
    np.testing.assert_array_equal(bundle.reduced_camera_matrix(*args, rows), single)


def test_solve_symmetric_falls_back_to_least_squares():
    from stereoseed.estimators._schur import solve_symmetric

    A = np.random.default_rng(0).normal(size=(6, 6))
    S = A @ A.T + np.eye(6)
    b = np.arange(6.0)
    np.testing.assert_allclose(S @ solve_symmetric(S, b), b, atol=1e-10)
    singular = np.zeros((3, 3))
    singular[0, 0] = 2.0  # not definite: Cholesky fails, least squares gives the minimum-norm answer
    np.testing.assert_allclose(solve_symmetric(singular, np.array([4.0, 0.0, 0.0])), [2.0, 0.0, 0.0])


def test_a_singular_point_block_gives_no_step_instead_of_an_error():
    from stereoseed.estimators._schur import eliminate_points, solve_symmetric

    V = np.zeros((1, 3, 3))
    V[0] -= 1e-12 * np.eye(3)  # cancels the damping's 1e-12: det 0
    Vinv, Y, rhs = eliminate_points(V, np.zeros((1, 3)), np.zeros((1, 7)), np.ones((1, 7, 3)), 0.0,
                                     np.zeros(1, np.int64), np.zeros(1, np.int64))
    assert not np.isfinite(Vinv).all()  # no ZeroDivisionError: the step is refused by its cost
    assert np.isnan(solve_symmetric(np.full((7, 7), np.inf), np.ones(7))).all()
