"""camera_uncertainty against two oracles: the dense normal equations of the whole problem
(cameras and points, a numerical Jacobian, inverted at once, no Schur complement) and the
spread of bundle_adjust's solutions over pixel-noise draws (Monte Carlo)."""
import json

import numpy as np
import pytest

from stereoseed.config import BundleConfig
from stereoseed.estimators.bundle import BundleProblem, bundle_adjust
from stereoseed.estimators.covariance import camera_uncertainty, parameter_names, point_regions
from stereoseed.geometry import models as camera_models
from stereoseed.geometry.projection import camera_center, decompose_projection, project
from geometry_helpers import box_points, ring_camera

ANGLES = (0.0, 25.0, 50.0, 75.0, 100.0)  # the first two fixed: the calibrated pair


def _scene(rng, model="focal", n_pts=60, angles=ANGLES, noise=0.0, n_fixed=2, points=None):
    """A ring of cameras (fixed ones first) all seeing n_pts box points (or ``points`` (M, 3));
    the free cameras in the model's family, the 'focal' and 'fixed' models relative to camera
    1's K."""
    cams = [ring_camera(a, f=800.0 + 10.0 * i) for i, a in enumerate(angles)]
    ref = cams[1][0]
    Ps = np.stack([c[3] for c in cams])
    free = np.arange(len(angles)) >= n_fixed
    for c in np.flatnonzero(free):
        Ps[c] = camera_models.project_to_model(Ps[c], model, ref)
    X = box_points(rng, n_pts) if points is None else points
    n_pts = len(X)
    oc = np.repeat(np.arange(len(angles)), n_pts)
    op = np.tile(np.arange(n_pts), len(angles))
    xy = np.concatenate([project(P, X) for P in Ps]) + rng.normal(0.0, noise, (len(oc), 2))
    return BundleProblem(Ps, free, X, np.ones(n_pts, bool), oc, op, xy, model, ref)


def _select(problem, keep):
    """The problem with only the observations ``keep`` (O,) bool."""
    return BundleProblem(problem.Ps, problem.free_cameras, problem.points, problem.free_points,
                         problem.obs_camera[keep], problem.obs_point[keep], problem.obs_xy[keep],
                         problem.model, problem.reference_K)


def _dense_oracle(problem, sigma):
    """Per free camera: its covariance block and the 1-sigma of its centre along its axes, from
    sigma^2 (J^T J)^-1 of all free parameters at once, J by central differences of the
    reprojection residuals, the camera as K(intrinsics) [exp([w]x) R0 | t]."""
    model, ref = problem.model, problem.reference_K
    ni, n = camera_models.N_INTRINSICS[camera_models.CameraModel(model)], camera_models.n_params(model)
    free = np.flatnonzero(problem.free_cameras)
    R0, theta0 = [], []
    for c in free:
        params = camera_models.params_from_projection(problem.Ps[c], model, ref)[0]
        R0.append(camera_models.rotation_from_vector(params[ni:ni + 3]))
        theta0.append(np.r_[params[:ni], 0.0, 0.0, 0.0, params[ni + 3:]])
    theta0 = np.concatenate(theta0 + [problem.points.ravel()])

    def cameras(theta):
        Ps = problem.Ps.copy()
        for i, c in enumerate(free):
            p = theta[i * n:(i + 1) * n]
            K = camera_models.Ks_from_intrinsics(p[None, :ni], model, ref)[0]
            Ps[c] = K @ np.hstack([camera_models.rotation_from_vector(p[ni:ni + 3]) @ R0[i], p[ni + 3:, None]])
        return Ps

    def residuals(theta):
        Ps, X = cameras(theta), theta[len(free) * n:].reshape(-1, 3)
        h = np.einsum("oij,oj->oi", Ps[problem.obs_camera], np.c_[X[problem.obs_point], np.ones(len(problem.obs_point))])
        return (h[:, :2] / h[:, 2:] - problem.obs_xy).ravel()

    def centres(theta):  # each free camera's centre in its own (initial) axes
        Ps = cameras(theta)
        return np.concatenate([R0[i] @ camera_center(Ps[c]) for i, c in enumerate(free)])

    def jacobian(f, theta):
        steps = 1e-6 * np.maximum(1.0, np.abs(theta))
        return np.stack([(f(theta + s * e) - f(theta - s * e)) / (2 * s) for s, e in zip(steps, np.eye(len(theta)))], 1)

    J = jacobian(residuals, theta0)
    cov = sigma ** 2 * np.linalg.inv(J.T @ J)
    Jc = jacobian(centres, theta0)
    pos = Jc @ cov @ Jc.T
    return ([cov[i * n:(i + 1) * n, i * n:(i + 1) * n] for i in range(len(free))],
            [np.sqrt(np.diag(pos)[3 * i:3 * i + 3]) for i in range(len(free))])


@pytest.mark.parametrize("model", ["free", "zero-skew", "focal", "fixed"])
def test_matches_the_dense_normal_equations(model):
    problem = _scene(np.random.default_rng(0), model, n_pts=30)
    result = camera_uncertainty(problem, sigma_px=0.5)
    assert result[:2] == [None, None]
    blocks, position = _dense_oracle(problem, 0.5)
    ni = camera_models.N_INTRINSICS[camera_models.CameraModel(model)]
    for u, block, pos in zip(result[2:], blocks, position):
        assert u.determined and u.parameters == parameter_names(model)
        d = np.sqrt(np.diag(block))
        np.testing.assert_allclose(np.sqrt(np.diag(u.covariance)), d, rtol=1e-5)
        np.testing.assert_allclose(u.covariance / np.outer(d, d), block / np.outer(d, d), atol=1e-5)  # correlations
        np.testing.assert_allclose(u.position_sigma, pos, rtol=1e-5)
        np.testing.assert_allclose(u.rotation_sigma_deg, np.degrees(d[ni:ni + 3]), rtol=1e-5)
        assert u.focal_sigma_px == (pytest.approx(d[0], rel=1e-5) if ni else None)


def _axes_errors(P_est, P_true):
    """Centre error along the true camera's axes, rotation error about them (deg), focal error."""
    K, R, _ = decompose_projection(P_true)
    Ke, Re, _ = decompose_projection(P_est)
    rot = camera_models.rotation_vector(Re @ R.T)  # R_est = exp([w]x) R: w about the camera's axes
    return R @ (camera_center(P_est) - camera_center(P_true)), np.degrees(rot), Ke[0, 0] - K[0, 0]


def test_agrees_with_monte_carlo_bundle_adjustment():
    """200 pixel-noise draws (0.5 px), each adjusted from the truth by plain least squares:
    the spread of the solutions is what the covariance predicts (the sample std of 200 draws
    is itself uncertain by ~5 %)."""
    rng = np.random.default_rng(1)
    truth = _scene(rng, "focal", n_pts=50)
    predicted = camera_uncertainty(truth, sigma_px=0.5)
    free = np.flatnonzero(truth.free_cameras)
    clean = truth.obs_xy.copy()
    errors = {c: ([], [], []) for c in free}
    config = BundleConfig(huber_px=1e9, max_iterations=30)  # least squares, as the covariance assumes
    for _ in range(200):
        noisy = BundleProblem(truth.Ps, truth.free_cameras, truth.points, truth.free_points, truth.obs_camera,
                              truth.obs_point, clean + rng.normal(0.0, 0.5, clean.shape), truth.model,
                              truth.reference_K)
        solved = bundle_adjust(noisy, config)
        for c in free:
            for store, e in zip(errors[c], _axes_errors(solved.Ps[c], truth.Ps[c])):
                store.append(e)
    for c in free:
        position, rotation, focal = (np.std(np.asarray(e), axis=0, ddof=1) for e in errors[c])
        np.testing.assert_allclose(position, predicted[c].position_sigma, rtol=0.2)
        np.testing.assert_allclose(rotation, predicted[c].rotation_sigma_deg, rtol=0.2)
        assert focal == pytest.approx(predicted[c].focal_sigma_px, rel=0.2)


def test_doubling_sigma_doubles_the_sigmas():
    problem = _scene(np.random.default_rng(2))
    one, two = camera_uncertainty(problem, sigma_px=0.5), camera_uncertainty(problem, sigma_px=1.0)
    for a, b in zip(one[2:], two[2:]):
        np.testing.assert_allclose(b.position_sigma, 2 * a.position_sigma, rtol=1e-12)
        np.testing.assert_allclose(b.rotation_sigma_deg, 2 * a.rotation_sigma_deg, rtol=1e-12)
        assert b.focal_sigma_px == pytest.approx(2 * a.focal_sigma_px, rel=1e-12)
        np.testing.assert_allclose(b.covariance, 4 * a.covariance, rtol=1e-12)


def test_sigma_estimated_from_the_residuals():
    rng = np.random.default_rng(3)
    problem = _scene(rng, n_pts=100, noise=0.5)
    solved = bundle_adjust(problem, BundleConfig(huber_px=1e9))
    at_solution = BundleProblem(solved.Ps, problem.free_cameras, solved.points, problem.free_points,
                                problem.obs_camera, problem.obs_point, problem.obs_xy, problem.model,
                                problem.reference_K)
    estimated, given = camera_uncertainty(at_solution), camera_uncertainty(at_solution, sigma_px=0.5)
    # 2 * 500 residuals - 3 * 7 - 300 parameters: the estimate's own spread is ~3 %
    assert estimated[2].sigma_px == pytest.approx(0.5, rel=0.1)
    for e, g in zip(estimated[2:], given[2:]):
        np.testing.assert_allclose(e.position_sigma, g.position_sigma * e.sigma_px / 0.5, rtol=1e-12)


def test_a_camera_seeing_more_points_is_more_certain():
    problem = _scene(np.random.default_rng(4), n_pts=80)
    half = ~((problem.obs_camera == 3) & (problem.obs_point % 2 == 1))  # camera 3 sees half the points
    full, fewer = camera_uncertainty(problem, 0.5)[3], camera_uncertainty(_select(problem, half), 0.5)[3]
    assert np.all(full.position_sigma < fewer.position_sigma)
    assert np.all(full.rotation_sigma_deg < fewer.rotation_sigma_deg)
    assert full.focal_sigma_px < fewer.focal_sigma_px
    # half the points, about sqrt(2) the sigma (not exactly: the points' own uncertainty is shared)
    assert 1.2 < np.mean(fewer.position_sigma / full.position_sigma) < 1.7


@pytest.mark.parametrize("seen", [2, 0])
def test_a_camera_with_too_few_observations_is_undetermined_not_a_number(seen):
    problem = _scene(np.random.default_rng(5), angles=ANGLES + (125.0,))
    few = (problem.obs_camera != 5) | (problem.obs_point < seen)  # camera 5: 2 points are 4 residuals for 7 parameters
    result = camera_uncertainty(_select(problem, few), sigma_px=0.5)
    weak = result[5]
    assert not weak.determined and f"{seen} usable observations" in weak.reason
    assert np.all(np.isinf(weak.position_sigma)) and np.all(np.isinf(weak.rotation_sigma_deg))
    assert np.isinf(weak.focal_sigma_px) and np.isnan(weak.covariance).all()
    d = weak.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["position_sigma"] == [None] * 3 and d["focal_sigma_px"] is None and d["reason"] == weak.reason
    # A camera with fewer residuals than parameters fits any of its points' moves: it tells the
    # others nothing, so they are as without it.
    without = camera_uncertainty(_select(problem, problem.obs_camera != 5), sigma_px=0.5)
    for c in (2, 3, 4):
        assert result[c].determined
        np.testing.assert_allclose(result[c].covariance, without[c].covariance, rtol=1e-6, atol=1e-12)
        ok = result[c].to_dict()
        json.dumps(ok, allow_nan=False)
        assert ok["reason"] is None and None not in ok["position_sigma"]


def test_one_fixed_camera_leaves_the_scale_free():
    result = camera_uncertainty(_scene(np.random.default_rng(6), n_fixed=1), sigma_px=0.5)
    assert result[0] is None
    for u in result[1:]:
        assert not u.determined and "singular" in u.reason
        assert np.all(np.isinf(u.position_sigma))


def test_points_seen_from_one_camera_are_skipped():
    rng = np.random.default_rng(7)
    problem = _scene(rng, n_pts=40)
    extra = box_points(rng, 6)  # seen by camera 2 only (the last three twice): no information on it
    points = np.r_[problem.points, extra]
    ids = 40 + np.r_[np.arange(6), np.arange(3, 6)]
    xy = np.r_[problem.obs_xy, project(problem.Ps[2], extra[ids - 40]) + rng.normal(0, 0.5, (len(ids), 2))]
    more = BundleProblem(problem.Ps, problem.free_cameras, points, np.ones(len(points), bool),
                         np.r_[problem.obs_camera, np.full(len(ids), 2)], np.r_[problem.obs_point, ids], xy,
                         problem.model, problem.reference_K)
    for a, b in zip(camera_uncertainty(problem, 0.5)[2:], camera_uncertainty(more, 0.5)[2:]):
        np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-9, atol=1e-15)


def test_cameras_moved_together_share_their_group_s_covariance():
    problem = _scene(np.random.default_rng(5), model="fixed", noise=0.3)
    n = len(problem.Ps)
    alone = camera_uncertainty(problem)
    eye = np.repeat(np.eye(6)[None], n, axis=0)
    own = camera_uncertainty(problem, groups=(np.arange(n), eye))  # one group per camera: no change
    for a, b in zip(alone[2:], own[2:]):
        np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-9)
    # cameras 3 and 4 as one body whose pose increment moves both alike (A = I; their own
    # residuals then disagree, as a rig's would not, but the algebra is the point): one
    # covariance for both, tighter than either alone (the pair's evidence adds up)
    together = camera_uncertainty(problem, groups=(np.array([0, 1, 2, 3, 3]), eye))
    np.testing.assert_allclose(together[3].covariance, together[4].covariance, rtol=1e-12)
    for c in (3, 4):
        assert np.all(np.diag(together[c].covariance) / together[c].sigma_px ** 2
                      < np.diag(alone[c].covariance) / alone[c].sigma_px ** 2)


def test_observations_sharing_a_window_count_once():
    """A camera whose every match is repeated 8 times a pixel or two away (as propagated matches
    are, pixel by pixel) is not measured better: counted one per 11 px cell, its sigma is that of
    the matches alone (to the digits: the information of an observation is its camera's and its
    point's, wherever its pixel, and nine of a ninth each make one); counted each, it shrinks (not by sqrt(9): the
    points' own uncertainty, which the repeats do not reduce, stays in it)."""
    from stereoseed.estimators.covariance import one_per_cell

    cell, sigma = 11.0, 0.5
    rng = np.random.default_rng(3)
    problem = _scene(rng, noise=sigma)
    # each match in the middle of its cell, and one match per cell (two in one cell would count once)
    centred = (np.floor(problem.obs_xy / cell) + 0.5) * cell
    problem.obs_xy[:] = centred + np.clip(problem.obs_xy - centred, -3.0, 3.0)
    problem = _select(problem, one_per_cell(problem.obs_camera, problem.obs_xy, cell) == 1.0)
    last = len(ANGLES) - 1
    mine = np.flatnonzero(problem.obs_camera == last)
    offsets = np.array([(dx, dy) for dx in (-2, 0, 2) for dy in (-2, 0, 2) if (dx, dy) != (0, 0)], float)
    repeats = np.repeat(problem.obs_xy[mine], 8, axis=0) + np.tile(offsets, (len(mine), 1))
    dense = BundleProblem(problem.Ps, problem.free_cameras, problem.points, problem.free_points,
                          np.r_[problem.obs_camera, np.full(len(repeats), last)],
                          np.r_[problem.obs_point, np.repeat(problem.obs_point[mine], 8)],
                          np.r_[problem.obs_xy, repeats], problem.model, problem.reference_K)
    share = one_per_cell(dense.obs_camera, dense.obs_xy, cell)
    others = dense.obs_camera != last  # one per cell; the last camera's: nine per cell
    assert np.all(share[others] == 1.0) and np.allclose(share[~others], 1 / 9)
    base = camera_uncertainty(problem, sigma_px=sigma)[last].position_sigma
    counted_each = camera_uncertainty(dense, sigma_px=sigma)[last].position_sigma
    counted_once = camera_uncertainty(dense, sigma_px=sigma, independent_cell_px=cell)[last].position_sigma
    np.testing.assert_allclose(counted_once, base, rtol=1e-6)
    assert np.all(counted_each < 0.85 * base)


def _solved(problem, xy):
    """The least-squares solution of ``problem`` with pixels ``xy``, as a problem at it."""
    noisy = BundleProblem(problem.Ps, problem.free_cameras, problem.points, problem.free_points, problem.obs_camera,
                          problem.obs_point, xy, problem.model, problem.reference_K)
    solved = bundle_adjust(noisy, BundleConfig(huber_px=1e9, max_iterations=30))
    return BundleProblem(solved.Ps, problem.free_cameras, solved.points, problem.free_points, problem.obs_camera,
                         problem.obs_point, xy, problem.model, problem.reference_K)


def _monte_carlo(truth, regions, draw, draws=80, measured_draws=10, cell_px=None):
    """The free cameras' real spread over ``draws`` least-squares solutions (cameras, 3 axes),
    and the model's, measured and reported position sigmas of the first ``measured_draws``
    (draws, cameras, 3 axes)."""
    free = np.flatnonzero(truth.free_cameras)
    centres = {c: [] for c in free}
    model, measured, reported = [], [], []
    for k in range(draws):
        at = _solved(truth, draw())
        for c in free:
            centres[c].append(np.asarray(_axes_errors(at.Ps[c], truth.Ps[c])[0]))
        if k < measured_draws:
            found = camera_uncertainty(at, point_clusters=regions, independent_cell_px=cell_px)
            model.append([found[c].model_position_sigma for c in free])
            measured.append([found[c].measured_position_sigma for c in free])
            reported.append([found[c].position_sigma for c in free])
    real = np.array([np.std(np.array(centres[c]), axis=0, ddof=1) for c in free])
    return real, np.array(model), np.array(measured), np.array(reported)


def test_the_measured_spread_covers_errors_shared_by_a_region_where_the_model_does_not():
    """Pixel errors shared by the points of a region in each image (the points one 20 px cell of
    image 0 sees: a region matched with one bias, as propagated matches are) plus a little
    independent noise; 80 Monte Carlo draws give the cameras' real spread. The model's sigma
    (from the residuals, each observation independent) falls well short of it; the spread
    measured from one draw's residuals over the regions (the sandwich) comes within its own
    sampling error, and the reported sigma is the larger of the two by its worst axis."""
    rng = np.random.default_rng(5)
    truth = _scene(rng, "focal", n_pts=1000)
    regions = point_regions(truth.obs_camera, truth.obs_point, truth.obs_xy, 1000, 20.0)  # cells of image 0
    n_regions = int(regions.max()) + 1
    assert n_regions > 80  # the sandwich needs many more regions than the 21 free parameters
    clean = truth.obs_xy.copy()
    region_of_obs = truth.obs_camera * n_regions + regions[truth.obs_point]

    def draw():
        shared = rng.normal(0.0, 0.5, (len(truth.Ps) * n_regions, 2))
        return clean + shared[region_of_obs] + rng.normal(0.0, 0.1, clean.shape)

    real, model, measured, reported = _monte_carlo(truth, regions, draw)
    np.testing.assert_allclose(reported.max(axis=2), np.maximum(model.max(axis=2), measured.max(axis=2)),
                               rtol=1e-9)
    model, measured = model.mean(axis=0), measured.mean(axis=0)
    assert np.all(model < 0.6 * real)  # the model counts every observation of an image independent
    np.testing.assert_allclose(measured, real, rtol=0.3)


def test_with_independent_errors_the_measured_spread_is_the_model_s():
    # over 10 draws (one draw's sandwich is itself uncertain by ~15 %), the variances agree
    rng = np.random.default_rng(6)
    truth = _scene(rng, "focal", n_pts=400)
    regions = np.arange(400) // 10
    ratios = []
    for _ in range(10):
        at = _solved(truth, truth.obs_xy + rng.normal(0.0, 0.5, truth.obs_xy.shape))
        found, plain = camera_uncertainty(at, point_clusters=regions), camera_uncertainty(at)
        for c in np.flatnonzero(truth.free_cameras):
            ratios.append((found[c].measured_position_sigma / found[c].model_position_sigma) ** 2)
            np.testing.assert_allclose(found[c].model_position_sigma, plain[c].position_sigma, rtol=1e-12)
            assert plain[c].measured_position_sigma is None
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.15)


def test_the_measured_spread_is_the_adjustment_s_when_the_model_counts_cells_once():
    # a dense patch (many points in a few cells, as propagated matches come): the model counts
    # each 11 px cell once, but the bundle adjustment weighs every observation fully, so the
    # spread measured is that of the adjustment's own estimate, whatever the model counts
    rng = np.random.default_rng(7)
    spread_out = box_points(rng, 300)
    patch = spread_out[:1] + rng.uniform(-0.04, 0.04, (300, 3)) * [1, 1, 0]  # on the top face, 8 cm across
    patch[:, 2] = spread_out[0, 2]
    truth = _scene(rng, "focal", points=np.vstack([spread_out, patch]))
    at = _solved(truth, truth.obs_xy + rng.normal(0.0, 0.5, truth.obs_xy.shape))
    regions = point_regions(at.obs_camera, at.obs_point, at.obs_xy, 600, 20.0)
    cells, plain = (camera_uncertainty(at, point_clusters=regions, independent_cell_px=cell) for cell in (11.0, None))
    for c in np.flatnonzero(truth.free_cameras):
        np.testing.assert_allclose(cells[c].measured_position_sigma, plain[c].measured_position_sigma, rtol=1e-9)
        assert np.all(cells[c].model_position_sigma > 1.2 * plain[c].model_position_sigma)  # the patch counted once a cell
