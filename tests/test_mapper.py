"""The mapper's operations on a small synthetic problem (exact correspondences, no images), the
way COLMAP tests its incremental mapper: register, triangulate, merge, filter, de-register,
close a loop, and a failed insertion leaves no trace."""
import numpy as np
import pytest

from geometry_helpers import ring_camera
from stereoseed.geometry.camera import camera_center, project
from stereoseed.config import Config, PipelineConfig
from stereoseed.features.harris import Features
from stereoseed.sfm.mapper import finish, initialise, insert_view
from stereoseed.matching.containers import Matches
from stereoseed.sfm.registration.base import CHAIN, MOTION_PRIOR, Registration, RegistrationFailure, register_view

SHAPE = (480, 640)


def box_surface(rng, n, half=0.17, height=0.44):
    """(points (n, 3), outward normals (n, 3)) on the four sides and the top of a box."""
    pts = rng.uniform([-half, -half, 0.0], [half, half, height], size=(n, 3))
    normals = np.zeros((n, 3))
    face = rng.integers(0, 5, n)
    for f, (axis, value) in enumerate(((0, half), (0, -half), (1, half), (1, -half), (2, height))):
        pts[face == f, axis] = value
        normals[face == f, axis] = np.sign(value)
    return pts, normals


class ExactSource:
    """Exact correspondences of known points (+ Gaussian pixel noise): interest points are the
    visible points' projections, matches the points two views share. ``blind`` views see
    nothing (an image that cannot be registered)."""

    def __init__(self, points, normals, Ps, noise_px=0.1, seed=0, blind=(), no_epipolar=()):
        self.points, self.normals, self.Ps = points, normals, Ps
        self.noise, self.seed, self.blind, self.no_epipolar = noise_px, seed, set(blind), set(no_epipolar)
        self.ids = {}
        # a distinct patch per physical point: the same point scores 1, others ~N(0, 1/64)
        desc = np.random.default_rng(seed).normal(size=(len(points), 64)).astype(np.float32)
        self.desc = desc / np.linalg.norm(desc, axis=1, keepdims=True)

    def features(self, index, image):
        P = self.Ps[index]
        x = project(P, self.points)
        facing = np.einsum("ij,ij->i", self.normals, camera_center(P) - self.points) > 0
        inside = np.all((x > 10) & (x < np.array(SHAPE[::-1]) - 10), axis=1)
        ids = np.flatnonzero(facing & inside) if index not in self.blind else np.zeros(0, np.int64)
        self.ids[index] = ids
        xy = x[ids] + np.random.default_rng([self.seed, index]).normal(0, self.noise, (len(ids), 2))
        n = len(ids)
        return Features(xy, self.desc[ids], np.ones(n, bool), np.ones(n), SHAPE)

    def match(self, a, b, fa, fb, F, image_width):
        if F is None and b in self.no_epipolar:  # as on repeated patterns: no robust F
            return Matches.empty()
        _, ia, ib = np.intersect1d(self.ids[a], self.ids[b], return_indices=True)
        return Matches(ia, ib, np.ones(len(ia)))


def ring(n_views, step_deg=20.0, seed=0, n_points=3000, blind=(), no_epipolar=(), targets=None):
    rng = np.random.default_rng(seed)
    points, normals = box_surface(rng, n_points)
    targets = targets or {}
    Ps = [ring_camera(30.0 + i * step_deg, height=0.7, target=targets.get(i, (0.0, 0.0, 0.2)))[3]
          for i in range(n_views)]
    images = [np.full(SHAPE + (3,), i, np.uint8) for i in range(len(Ps))]  # distinct images (the pair check)
    names = [f"v{i}.png" for i in range(n_views)]
    return images, names, Ps, ExactSource(points, normals, Ps, blind=blind, no_epipolar=no_epipolar)


def centre_errors(recon, Ps):
    return np.array([np.linalg.norm(camera_center(v.P) - camera_center(P))
                     for v, P in zip(recon.views[2:], Ps[2:]) if v.registered])


def state(recon):
    """Everything an insertion may change, as comparable arrays."""
    views = [(v.P, v.features, v.point_of_feature.copy(), v.image, v.rotated_180, v.camera_model, v.zoomed)
             for v in recon.views]
    return (recon.points.copy(), recon.colors.copy(), recon.alive.copy(), recon.obs_view.copy(),
            recon.obs_feature.copy(), recon.obs_point.copy(), recon.obs_linked.copy(), views)


def assert_same_state(a, b):
    for x, y in zip(a[:7], b[:7]):
        np.testing.assert_array_equal(x, y)
    for va, vb in zip(a[7], b[7]):
        assert (va[0] is None) == (vb[0] is None)
        if va[0] is not None:
            np.testing.assert_array_equal(va[0], vb[0])
        assert va[1] is vb[1] and va[3] is vb[3]  # the same features and image objects
        np.testing.assert_array_equal(va[2], vb[2])
        assert va[4:] == vb[4:]


@pytest.fixture(scope="module")
def started():
    """A ring of 8 views, the pair and 2 insertions done (accurate mode)."""
    images, names, Ps, source = ring(8)
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in (2, 3):
        assert insert_view(recon, k, cfg)["status"] == "registered"
    return recon, Ps, cfg


def test_initialise_triangulates_the_shared_points_of_the_pair():
    images, names, Ps, source = ring(3)
    recon, report = initialise(images, names, Ps[:2], Config(), source)
    shared = len(np.intersect1d(source.ids[0], source.ids[1]))
    assert report["new_points"] == len(recon.points) and len(recon.points) >= 0.95 * shared
    X_true = source.points[source.ids[0][recon.obs_feature[recon.obs_view == 0]]]
    assert np.abs(recon.points - X_true).max() < 0.002  # 0.1 px noise at 1.4 m
    assert np.all(recon.views[0].point_of_feature[recon.obs_feature[recon.obs_view == 0]] >= 0)


def test_registration_finds_the_camera_and_changes_nothing(started):
    recon, Ps, cfg = started
    before = state(recon)
    found = register_view(recon, 4, cfg.resolved())
    assert isinstance(found, Registration) and found.found_by == CHAIN
    # resection alone, before any BA: the focal length trades against the depth (measured 2.7 mm)
    assert np.linalg.norm(camera_center(found.P) - camera_center(Ps[4])) < 0.006
    assert found.chained_points >= 100 and found.resection.inliers.sum() >= 100
    assert_same_state(before, state(recon))
    assert recon.views[4].features is None and not recon.views[4].registered


def test_an_image_that_cannot_be_registered_leaves_no_trace():
    images, names, Ps, source = ring(6, blind=(3,))
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    insert_view(recon, 2, cfg)
    before = state(recon)
    report = insert_view(recon, 3, cfg)
    assert report["status"] == "failed" and "v3.png" in report["reason"]
    assert isinstance(register_view(recon, 3, cfg.resolved()), RegistrationFailure)
    assert_same_state(before, state(recon))
    assert recon.views[3].status.startswith("failed: ")
    # the walk goes on from the last registered view, two steps away
    assert insert_view(recon, 4, cfg)["status"] == "registered"
    assert centre_errors(recon, Ps).max() < 0.006  # measured 0.9 and 3.0 mm (a free focal length, no final BA)


def test_the_step_by_step_api_survives_a_failing_image():
    images, names, Ps, source = ring(7, blind=(4,))
    cfg = Config(pipeline=PipelineConfig(mode="paper"))
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    statuses = [insert_view(recon, k, cfg)["status"] for k in range(2, 7)]
    assert statuses == ["registered", "registered", "failed", "registered", "registered"]
    finish(recon, cfg)
    assert recon.registered_views == [0, 1, 2, 3, 5, 6]


def test_the_paper_mode_keeps_two_view_points_and_unlinked_chained_observations():
    images, names, Ps, source = ring(5)
    cfg = Config(pipeline=PipelineConfig(mode="paper"))
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    insert_view(recon, 2, cfg)
    unlinked = ~recon.obs_linked
    # the chained old points are observed in view 2 for the cost only; their interest points
    # stand for the new two-view points, through which the next insertion chains
    assert unlinked.any() and set(recon.obs_view[unlinked]) <= {1, 2}
    v2 = recon.views[2]
    stands_for = v2.point_of_feature[recon.obs_feature[unlinked & (recon.obs_view == 2)]]
    assert np.all(stands_for != recon.obs_point[unlinked & (recon.obs_view == 2)])
    live = recon.alive & (recon.track_lengths() > 0)
    assert np.all(recon.track_lengths()[live] >= 2)


def test_a_closed_ring_merges_the_points_reconstructed_twice():
    images, names, Ps, source = ring(18)  # 18 x 20 degrees: back to the start
    recon, report = reconstruct_ring(images, names, Ps, source)
    closure = report["loop_closure"]
    assert closure["closed"] and closure["merges"] > 100 and closure["links"] > 0
    pts, _ = recon.live_points()
    # after merging, no physical point is there twice (exact correspondences: twins lie < 2 mm apart)
    from scipy.spatial import cKDTree
    assert len(cKDTree(pts).query_pairs(0.0005)) < 0.01 * len(pts)
    assert centre_errors(recon, Ps).max() < 0.002


def reconstruct_ring(images, names, Ps, source):
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    for k in range(2, len(images)):
        assert insert_view(recon, k, cfg)["status"] == "registered"
    return recon, finish(recon, cfg)


def test_without_epipolar_geometry_the_motion_prior_places_the_camera():
    images, names, Ps, source = ring(6, step_deg=10.0, no_epipolar=(4,))
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    reports = [insert_view(recon, k, cfg) for k in range(2, 6)]
    assert reports[2]["matches"] == 0 and reports[2]["registered_by"] == MOTION_PRIOR
    assert reports[2]["motion_prior_search"]["radius_fraction"] == min(cfg.motion_prior.radius_fractions)
    assert centre_errors(recon, Ps).max() < 0.003


def test_the_wide_search_finds_a_camera_the_prediction_misses():
    # image 4 looks 12 cm to the side of the others' target: every point lands ~70 px from its
    # predicted pixel, beyond the near search (8 % of 640 px), within the wide one (16 %)
    images, names, Ps, source = ring(6, step_deg=10.0, no_epipolar=(4,), targets={4: (0.12, -0.05, 0.2)})
    cfg = Config()
    recon, _ = initialise(images, names, Ps[:2], cfg, source)
    reports = [insert_view(recon, k, cfg) for k in range(2, 6)]
    assert reports[2]["registered_by"] == MOTION_PRIOR, reports[2]
    assert reports[2]["motion_prior_search"]["radius_fraction"] == max(cfg.motion_prior.radius_fractions)
    assert centre_errors(recon, Ps).max() < 0.003


def _raising(error):
    def raise_it(*args, **kwargs):
        raise error
    return raise_it


@pytest.mark.parametrize("module, function", [("sfm.registration.base", "implausible_motion"), ("sfm.modes", "adjust")])
def test_a_numerical_failure_fails_the_image_and_changes_nothing(started, monkeypatch, module, function):
    # during the registration (nothing committed yet) or after the commit (rolled back)
    import importlib

    recon, Ps, cfg = started
    before = state(recon)
    monkeypatch.setattr(importlib.import_module(f"stereoseed.{module}"), function,
                        _raising(np.linalg.LinAlgError("Singular matrix")))
    report = insert_view(recon, 4, cfg)
    assert report["status"] == "failed" and "numerical failure" in report["reason"]
    assert_same_state(before, state(recon))
    assert not recon.views[4].registered


def test_an_unexpected_error_after_the_commit_propagates_with_the_model_restored(started, monkeypatch):
    import stereoseed.sfm.modes

    recon, Ps, cfg = started
    before = state(recon)
    monkeypatch.setattr(stereoseed.sfm.modes, "adjust", _raising(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        insert_view(recon, 4, cfg)
    assert_same_state(before, state(recon))


def test_a_right_calibration_is_kept_when_the_robust_F_locks_onto_a_wrong_period():
    # plain box, scene seed 5: the pair's 32 matches found without the calibration follow a
    # robust F fitted to period-shifted squares (12 % on the calibrated epipolar lines); the
    # calibration itself matches 118 points, and the pair must be accepted
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    scene = render_scene(SceneConfig(textured=False, seed=5, n_images=2))
    recon, report = initialise(scene.images, scene.names, scene.P[:2], Config())
    assert report["new_points"] >= 100


def test_a_view_left_without_enough_observations_is_dropped_at_the_end(small_box_scene):
    # a weakly placed view can lose its observations to outlier removal until nothing determines
    # its camera; the finishing step then deregisters it and says why
    from stereoseed.sfm.mapper import _drop_undetermined_views
    from stereoseed.pipeline import reconstruct

    scene = small_box_scene.prefix(5)
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert _drop_undetermined_views(recon, Config()) == {}  # a sound run keeps every view
    seen = np.flatnonzero(recon.obs_view == 3)
    cut = np.zeros(len(recon.obs_view), bool)
    cut[seen[5:]] = True  # view 3 keeps 5 observations
    recon.remove_observations(cut)
    dropped = _drop_undetermined_views(recon, Config())
    assert list(dropped) == [scene.names[3]] and "5 observations" in dropped[scene.names[3]]
    assert recon.views[3].P is None and recon.views[3].status.startswith("failed")
    assert all(recon.views[k].P is not None for k in (0, 1, 2, 4))


def test_local_ba_holds_the_calibrated_intrinsics_until_a_zoom_is_found():
    """accurate mode, "focal" model: the BA after an insertion runs on the "fixed" model while no
    image after the pair was found zoomed; then, and in paper mode, on the run's model."""
    from stereoseed.sfm.modes import mode_of
    from stereoseed.sfm.reconstruction import Reconstruction, View

    def _unzoomed_held(recon, cfg):  # the BA configuration the mode gives after an insertion
        return mode_of(cfg).adjustment_config(recon, cfg)

    P = np.hstack([np.eye(3), np.zeros((3, 1))])
    recon = Reconstruction([View(name=f"v{i}", P=P) for i in range(4)])
    cfg = Config().resolved()
    assert _unzoomed_held(recon, cfg).pipeline.camera_model == "fixed"
    recon.views[3].zoomed = True
    assert _unzoomed_held(recon, cfg) is cfg
    recon.views[3].zoomed = False
    paper = Config(pipeline=PipelineConfig(mode="paper")).resolved()
    assert _unzoomed_held(recon, paper) is paper
    no_hold = Config(pipeline=PipelineConfig(hold_unzoomed=False)).resolved()
    assert _unzoomed_held(recon, no_hold) is no_hold
