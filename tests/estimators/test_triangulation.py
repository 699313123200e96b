import cv2
import numpy as np
from hypothesis import given, settings, strategies as st

from stereoseed.geometry.projection import project
from stereoseed.estimators.triangulation import triangulate, triangulate_linear, triangulate_tracks
from geometry_helpers import box_points, ring_camera


def _pair(angle=20.0):
    return ring_camera(0.0)[3], ring_camera(angle, f=870.0)[3]


def test_exact_data_recovers_points():
    rng = np.random.default_rng(0)
    P1, P2 = _pair()
    X = box_points(rng, 500)
    x = np.stack([project(P1, X), project(P2, X)])
    res = triangulate(np.stack([P1, P2]), x)
    assert np.max(np.abs(res.points - X)) < 1e-9
    assert np.nanmax(res.errors) < 1e-8
    assert np.all(res.depths > 0)
    assert np.all(res.angles > 10) and np.all(res.angles < 30)


def test_agrees_with_opencv():
    rng = np.random.default_rng(1)
    P1, P2 = _pair()
    X = box_points(rng, 200)
    x1 = project(P1, X) + rng.normal(0, 0.5, (200, 2))
    x2 = project(P2, X) + rng.normal(0, 0.5, (200, 2))
    ours = triangulate_linear(np.stack([P1, P2]), np.stack([x1, x2]))
    h = cv2.triangulatePoints(P1, P2, x1.T, x2.T)
    theirs = (h[:3] / h[3]).T
    # both solve the same homogeneous system up to row weighting: agree to well under the noise
    assert np.median(np.linalg.norm(ours - theirs, axis=1)) < 1e-4


def test_lm_refinement_reduces_reprojection_error_to_optimum():
    rng = np.random.default_rng(2)
    Ps = np.stack([ring_camera(a, f=800 + 10 * a)[3] for a in (0.0, 15.0, 30.0)])
    X = box_points(rng, 300)
    x = np.stack([project(P, X) for P in Ps]) + rng.normal(0, 1.0, (3, 300, 2))
    linear = triangulate_linear(Ps, x)
    res = triangulate(Ps, x)
    lin_err = np.linalg.norm(np.stack([project(P, linear) for P in Ps]) - x, axis=2)
    assert np.sum(res.errors ** 2) < np.sum(lin_err ** 2)
    # ML: residual DOF per point is 2V - 3 = 3, so E[sum r^2] = 3 sigma^2 per point
    assert abs(np.mean(np.sum(res.errors ** 2, axis=0)) / 3.0 - 1.0) < 0.15


def test_mask_handles_partial_tracks_and_filters():
    rng = np.random.default_rng(3)
    Ps = np.stack([ring_camera(a)[3] for a in (0.0, 20.0, 40.0)])
    X = box_points(rng, 100)
    x = np.stack([project(P, X) for P in Ps])
    mask = np.ones((3, 100), bool)
    mask[2, :50] = False
    x[2, :50] = 1e6  # garbage where unobserved must not matter
    res = triangulate(Ps, x, mask)
    assert np.max(np.abs(res.points - X)) < 1e-8
    assert np.all(np.isnan(res.errors[2, :50]))
    assert res.valid(1.0, 1.0, mask).all()
    # a point behind camera 0 is rejected
    res.depths[0, 7] = -1.0
    assert not res.valid(1.0, 1.0, mask)[7]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.1, 0.6)),
                min_size=1, max_size=30),
       st.floats(3.0, 60.0))
def test_random_points_round_trip(points, angle):
    X = np.array(points)
    P1, P2 = _pair(angle)
    x = np.stack([project(P1, X), project(P2, X)])
    res = triangulate(np.stack([P1, P2]), x)
    assert np.allclose(res.points, X, atol=1e-7)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=1, max_size=20))
def test_garbage_pixels_never_crash(pixels):
    x = np.array(pixels, dtype=float)
    P1, P2 = _pair()
    res = triangulate(np.stack([P1, P2]), np.stack([x, x[::-1]]))
    assert res.points.shape == (len(x), 3)
    res.valid(2.0, 1.0)  # callable whatever came out


def test_tracks_of_any_length_agree_with_the_batched_refinement():
    """triangulate_tracks (observations grouped by point, compiled LM) against triangulate
    (every point in every view, a mask): the same optimum on noisy tracks of 2 to 4 views;
    a point seen once is NaN."""
    rng = np.random.default_rng(3)
    Ps = np.stack([ring_camera(a, f=870.0)[3] for a in (0.0, 15.0, 30.0, 45.0)])
    X = box_points(rng, 60)
    x = np.stack([project(P, X) for P in Ps]) + rng.normal(0, 0.5, (4, 60, 2))
    seen = np.ones((4, 60), bool)
    seen[2:, :20] = False  # two views
    seen[3, 20:40] = False  # three views
    seen[1:, 59] = False  # one view
    ref = triangulate(Ps, x, seen, iterations=20).points
    view, point = np.nonzero(seen)
    order = np.argsort(point, kind="stable")[::-1]  # any order of the observations
    got = triangulate_tracks(Ps[view[order]], x[view[order], point[order]], point[order], 60, iterations=20)
    assert np.all(np.isnan(got[59]))
    np.testing.assert_allclose(got[:59], ref[:59], atol=1e-7)
