"""Tracks: new points from a pair, re-triangulation from a whole track, the three-view choice's
one-to-one selection, and tracking by projection only where the source can track."""
import numpy as np

from ring_helpers import ring
from stereoseed.config import Config
from stereoseed.matching.containers import Matches
from stereoseed.sfm.mapper import initialise, insert_view
from stereoseed.sfm.tracks import _one_to_one, add_two_view_points, retriangulate, track_by_projection


def _started(n=5):
    images, names, Ps, source = ring(n)
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in range(2, n):
        assert insert_view(recon, k, cfg, source)["status"] == "registered"
    return recon, source, cfg


def _truth(recon, source):
    """The true position of each point, from the exact source's ids of its first observation."""
    first = np.unique(recon.obs_point, return_index=True)
    X = np.full((len(recon.points), 3), np.nan)
    v, f = recon.obs_view[first[1]], recon.obs_feature[first[1]]
    X[first[0]] = np.array([source.points[source.ids[vi][fi]] for vi, fi in zip(v, f)])
    return X


def test_two_view_points_lie_on_the_truth_and_link_as_asked():
    recon, source, cfg = _started()
    a, b = 2, 4
    # the exact matches between a and b
    _, ia, ib = np.intersect1d(source.ids[a], source.ids[b], return_indices=True)
    m = Matches(ia, ib, np.ones(len(ia)))
    before, stood_for = len(recon.points), recon.views[a].point_of_feature.copy()
    ids = add_two_view_points(recon, a, b, m, cfg.triangulation, colour_view=b, link_a=False)
    assert len(ids) > 0.8 * len(m) and np.array_equal(ids, np.arange(before, before + len(ids)))
    X_true = source.points[source.ids[b][recon.obs_feature[(recon.obs_view == b) & (recon.obs_point >= before)]]]
    assert np.max(np.linalg.norm(recon.points[ids] - X_true, axis=1)) < 0.003  # 0.1 px noise, 40 degrees apart
    # b's interest points now stand for the new points; a's (link_a False) for what they stood for
    in_b = (recon.obs_view == b) & (recon.obs_point >= before)
    np.testing.assert_array_equal(recon.views[b].point_of_feature[recon.obs_feature[in_b]], recon.obs_point[in_b])
    np.testing.assert_array_equal(recon.views[a].point_of_feature, stood_for)


def test_retriangulation_brings_a_displaced_point_back_and_leaves_a_hopeless_one():
    recon, source, cfg = _started()
    long = np.flatnonzero(recon.alive & (recon.track_lengths() >= 3))[:50]
    X_true = _truth(recon, source)[long]
    recon.points[long] += 0.02  # 2 cm off: every observation disagrees
    retriangulate(recon, np.sort(long), cfg.triangulation)
    assert np.max(np.linalg.norm(recon.points[long] - X_true, axis=1)) < 0.003
    # a point whose observations cannot agree keeps its position
    p = long[0]
    obs = np.flatnonzero(recon.obs_point == p)
    v0 = recon.views[recon.obs_view[obs[0]]]
    v0.features.points[recon.obs_feature[obs[0]]] += 40.0  # one observation 40 px off
    kept = recon.points[p].copy()
    retriangulate(recon, np.array([p]), cfg.triangulation)
    np.testing.assert_array_equal(recon.points[p], kept)


def test_the_three_view_choice_uses_each_interest_point_once():
    ia, ib, ic = np.array([0, 0, 1, 2]), np.array([5, 6, 5, 7]), np.array([9, 8, 7, 9])
    keep = _one_to_one(ia, ib, ic, np.array([0, 1, 2, 3]))
    np.testing.assert_array_equal(keep, [0])  # 1 reuses a's 0, 2 reuses b's 5, 3 reuses c's 9
    keep = _one_to_one(ia, ib, ic, np.array([3, 2, 1, 0]))
    np.testing.assert_array_equal(keep, [3, 2, 1])


def test_a_source_that_cannot_track_tracks_nothing():
    recon, source, cfg = _started(4)
    assert not hasattr(source, "track")  # the exact source declares no tracking
    n_obs = len(recon.obs_point)
    assert len(track_by_projection(recon, 3, [2, 1], cfg.tracking, source)) == 0 and len(recon.obs_point) == n_obs
