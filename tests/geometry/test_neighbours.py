"""Radius searches in the image plane against scipy's cKDTree (the oracle)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from stereoseed.geometry.neighbours import nearest_within, repeats_earlier


def _scene(seed):
    """Interest points of a 640x480 image, some in tight clusters (a corner detected twice),
    and queries: near the points, anywhere, far outside the image, not finite."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([0, 0], [640, 480], (1500, 2))
    points = np.vstack([points, points[:200] + rng.normal(0, 0.4, (200, 2))])
    queries = np.vstack([points[rng.integers(0, len(points), 700)] + rng.normal(0, 1.5, (700, 2)),
                         rng.uniform([-50, -50], [700, 550], (300, 2)),
                         [[1e12, 5.0], [-1e15, -1e15], [np.nan, 3.0], [4.0, np.inf]]])
    return points, queries


@pytest.mark.parametrize("seed,radius", [(0, 1.0), (1, 2.0), (2, 0.3), (3, 40.0)])
def test_nearest_within_is_cKDTrees_nearest_within_the_radius(seed, radius):
    points, queries = _scene(seed)
    dist, index = nearest_within(points, queries, radius)
    finite = np.isfinite(queries).all(axis=1)
    want_d, want_i = cKDTree(points).query(queries[finite])
    within = want_d <= radius
    np.testing.assert_array_equal(np.isfinite(dist[finite]), within)
    np.testing.assert_allclose(dist[finite][within], want_d[within], rtol=1e-12)
    np.testing.assert_array_equal(index[finite][within], want_i[within])
    assert np.all(index[finite][~within] == len(points)) and np.all(np.isinf(dist[~finite]))
    assert within.sum() > 10 and (~within).sum() > 10  # both cases met


def test_a_point_at_exactly_the_radius_is_within_and_ties_take_the_lowest_index():
    points = np.array([[3.0, 4.0], [10.0, 10.0], [-3.0, -4.0], [0.0, 5.0 + 1e-9]])
    dist, index = nearest_within(points, np.array([[0.0, 0.0], [0.0, 100.0]]), 5.0)
    assert dist[0] == 5.0 and index[0] == 0  # points 0 and 2 both at 5: the lower index
    assert np.isinf(dist[1]) and index[1] == len(points)
    assert nearest_within(points, np.zeros((0, 2)), 1.0)[0].shape == (0,)
    assert np.all(nearest_within(np.zeros((0, 2)), points, 1.0)[1] == 0)
    for radius in (0.0, -1.0, np.inf):
        with pytest.raises(ValueError):
            nearest_within(points, np.zeros((0, 2)), radius)
    # a point that is not finite is nobody's neighbour, and repeats nothing
    with_nan = np.vstack([[[0.5, 0.0]], [[np.nan, 0.0]], points, [[np.inf, 5.0]]])
    dist, index = nearest_within(with_nan, np.array([[0.0, 0.0], [9.0, 9.0]]), 1.0)
    assert index[0] == 0 and dist[0] == 0.5 and index[1] == len(with_nan)
    assert np.all(np.isinf(nearest_within(np.full((3, 2), np.nan), points, 1.0)[0]))
    np.testing.assert_array_equal(repeats_earlier(np.array([[0.0, 0.0], [np.nan, 0.0], [0.1, 0.0], [np.nan, 0.0]]), 1.0),
                                  [False, False, True, False])


def test_a_tiny_radius_over_a_wide_span_stays_exact():
    """Cells are never smaller than span / 2^20: the int64 cell keys cannot overflow, and the
    searches stay exact (a coarser grid only scans more points)."""
    rng = np.random.default_rng(7)
    points = np.vstack([rng.uniform(0, 1e9, (300, 2)), [[5e8, 5e8], [5e8 + 3e-4, 5e8]]])
    dist, index = nearest_within(points, np.array([[5e8 + 1e-4, 5e8], [1e9 + 1.0, 0.0]]), 1e-3)
    assert index[0] == len(points) - 2 and abs(dist[0] - 1e-4) < 1e-6 and np.isinf(dist[1])
    repeats = repeats_earlier(points, 1e-3)
    assert repeats[-1] and repeats.sum() == 1


@pytest.mark.parametrize("seed,radius", [(0, 1.0), (4, 0.5), (5, 3.0)])
def test_repeats_earlier_drops_the_higher_index_of_every_close_pair(seed, radius):
    points, _ = _scene(seed)
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    want = np.zeros(len(points), bool)
    want[pairs.max(axis=1)] = True
    got = repeats_earlier(points, radius)
    np.testing.assert_array_equal(got, want)
    assert 10 < got.sum() < len(points) - 10
    # a chain a - b - c with a, c apart: b and c both repeat an earlier point
    chain = np.array([[0.0, 0.0], [0.9, 0.0], [1.8, 0.0], [50.0, 50.0]])
    np.testing.assert_array_equal(repeats_earlier(chain, 1.0), [False, True, True, False])
