"""The data model: the observation manager keeps its invariants (one 3D point per interest
point, unlinked observations explicit, dead points keep their index) and grows without
copying everything on each append."""
import numpy as np
import pytest

from geometry_helpers import ring_camera
from stereoseed.geometry.projection import decompose_projection
from stereoseed.features.harris import Features
from stereoseed.scene.camera_life import Flag, FlagKind
from stereoseed.scene.reconstruction import Reconstruction, View, eq14


def _views(n_views=3, n_features=10):
    views = []
    for i in range(n_views):
        f = Features(np.random.default_rng(i).uniform(0, 600, (n_features, 2)), np.zeros((n_features, 1), np.float32),
                     np.ones(n_features, bool), np.ones(n_features), (480, 640))
        views.append(View(f"v{i}", features=f, point_of_feature=np.full(n_features, -1, np.int64),
                          P=ring_camera(20.0 * i)[3]))
    return Reconstruction(views)


def test_points_grow_past_the_initial_capacity_without_losing_any():
    recon = _views()
    chunks = [np.random.default_rng(i).normal(size=(n, 3)) for i, n in enumerate((5, 20, 1, 100))]
    ids = [recon.add_points(c, np.full((len(c), 3), i, np.uint8)) for i, c in enumerate(chunks)]
    np.testing.assert_array_equal(np.concatenate(ids), np.arange(126))
    np.testing.assert_array_equal(recon.points, np.vstack(chunks))
    assert recon.colors[-1].tolist() == [3, 3, 3] and recon.alive.all() and recon.points.shape == (126, 3)
    recon.points[ids[1]] += 1.0  # adjusting in place through the view works
    np.testing.assert_array_equal(recon.points[ids[1]], chunks[1] + 1.0)


def test_linked_and_unlinked_observations():
    recon = _views()
    ids = recon.add_points(np.zeros((4, 3)), np.zeros((4, 3)))
    recon.add_observations(0, [0, 1, 2, 3], ids)
    recon.add_observations(1, [5, 6], ids[:2])
    recon.add_observations(1, [7], ids[2:3], link=False)  # for the cost only
    assert recon.views[1].point_of_feature[[5, 6, 7]].tolist() == [0, 1, -1]
    assert recon.obs_linked.tolist() == [True] * 6 + [False]
    np.testing.assert_array_equal(recon.points_seen_by(1), [0, 1, 2])
    # removing an unlinked observation leaves the interest point's own link alone
    recon.views[1].point_of_feature[7] = 3
    recon.remove_observations(recon.obs_linked == False)  # noqa: E712
    assert recon.views[1].point_of_feature[7] == 3 and len(recon.obs_view) == 6


def test_removing_points_unlinks_their_interest_points_and_keeps_indices():
    recon = _views()
    ids = recon.add_points(np.zeros((3, 3)), np.zeros((3, 3)))
    for v in range(3):
        recon.add_observations(v, ids + v, ids)
    recon.remove_points(ids[1:2])
    assert not recon.alive[1] and recon.alive[[0, 2]].all() and len(recon.points) == 3
    assert 1 not in recon.obs_point
    assert recon.views[0].point_of_feature[1] == -1 and recon.views[2].point_of_feature[3] == -1
    assert recon.track_lengths().tolist() == [3, 0, 3]


def test_filtering_drops_outliers_then_points_seen_once():
    recon = _views()
    ids = recon.add_points(np.zeros((2, 3)), np.zeros((2, 3)))
    recon.add_observations(0, [0, 1], ids)
    recon.add_observations(1, [0, 1], ids)
    recon.add_observations(2, [0], ids[:1])
    bad = (recon.obs_view == 1) & (recon.obs_point == 1)
    assert recon.filter_observations(bad) == 1
    assert recon.alive.tolist() == [True, False]  # point 1 was left with one view
    assert recon.track_lengths().tolist() == [3, 0]


def test_merging_moves_observations_unless_a_view_sees_both():
    recon = _views(4)
    ids = recon.add_points(np.zeros((3, 3)), np.zeros((3, 3)))
    recon.add_observations(0, [0], ids[:1])
    recon.add_observations(1, [0], ids[:1])
    recon.add_observations(2, [4], ids[1:2])
    recon.add_observations(3, [4], ids[1:2])
    recon.add_observations(1, [9], ids[2:3])  # view 1 already sees point 0: 2 is another point
    recon.add_observations(3, [9], ids[2:3])
    assert recon.merge_points(np.array([0, 0]), np.array([1, 2])) == 1
    assert recon.alive.tolist() == [True, False, True]
    assert recon.track_lengths().tolist() == [4, 0, 2]
    assert recon.views[2].point_of_feature[4] == 0 and recon.views[3].point_of_feature[4] == 0


def test_a_withdrawal_and_checkpoint_restore():
    recon = _views()
    recon.register(2, recon.views[2].camera, "motion prior", recon.views[2].features,
                   np.zeros((480, 640, 3), np.uint8), False, None, False, Flag.parse("ambiguous: repeated structure (as if)"))
    ids = recon.add_points(np.ones((2, 3)), np.zeros((2, 3)))
    for v in range(3):
        recon.add_observations(v, [0, 1], ids)
    saved = recon.checkpoint()
    P2 = recon.views[2].P.copy()
    recon.withdraw(2, "v2: withdrawn")
    assert recon.views[2].found_by is None and recon.views[2].placement_flag is None
    recon.points[:] = 7.0
    assert not recon.views[2].registered and len(recon.views[2].point_of_feature) == 0
    assert recon.track_lengths().tolist() == [2, 2]
    recon.restore(saved)
    np.testing.assert_array_equal(recon.views[2].P, P2)
    assert recon.views[2].found_by == "motion prior" and recon.views[2].placement_flag.kind == FlagKind.AMBIGUOUS
    assert recon.track_lengths().tolist() == [3, 3] and np.all(recon.points == 1.0)
    assert recon.views[2].point_of_feature[:2].tolist() == [0, 1]
    recon.add_points(np.zeros((40, 3)), np.zeros((40, 3)))  # the restored arrays still grow
    assert len(recon.points) == 42


def test_a_view_decomposes_its_camera_once_per_camera():
    view = View("a", P=ring_camera(10.0)[3])
    K = view.K
    assert view.K is K  # cached
    np.testing.assert_allclose(K, decompose_projection(view.P)[0])
    view.P = ring_camera(20.0, f=900.0)[3]
    assert view.focal == pytest.approx(900.0) and view.K is not K


def test_eq14_divides_by_images_times_points():
    assert eq14(12.0, 3, 4) == 1.0 and eq14(5.0, 0, 0) == 5.0
