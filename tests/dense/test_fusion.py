"""Multi-view fusion of the pairs' clouds (stereoseed.dense.fusion, issue 50): a point every
other pair sees on the same surface is confirmed and averaged; a floater in front of the surface
the other pairs see is contradicted and has no support."""
import numpy as np
import pytest

from stereoseed.dense.config import DenseConfig
from stereoseed.dense.fusion import PairCloud, PairSpool, check_views, depth_sigma
from stereoseed.geometry.projection import normalize_projection

WIDTH, HEIGHT, FOCAL = 160, 120, 200.0


def _camera(x: float) -> np.ndarray:
    """A camera at (x, 0, 0) looking along +z (the wall at z = 5 fills its image)."""
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
    return K @ np.hstack([np.eye(3), [[-x], [0.0], [0.0]]])


def _pair_cloud(cameras, a, b, rng, noise_m, floaters=np.zeros(0, np.int64)):
    """Pair (a, b)'s points: the wall z = 5 at every pixel of view a, moved along a's ray by
    Gaussian noise; the points of rows ``floaters`` put 1-3 m in front of the wall."""
    P = cameras[a]
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    pixels = np.c_[u.ravel(), v.ravel()]
    rays = np.c_[(pixels - [WIDTH / 2, HEIGHT / 2]) / FOCAL, np.ones(len(pixels))]
    centre = np.array([-P[0, 3] / FOCAL, 0.0, 0.0])
    depth = 5.0 + rng.normal(0, noise_m, len(pixels))
    depth[floaters] -= rng.uniform(1.0, 3.0, len(floaters))
    points = centre + rays * depth[:, None]
    baseline = abs(-cameras[b][0, 3] / FOCAL - centre[0])
    angles = np.full(len(points), np.degrees(np.arctan2(baseline, 5.0)))
    return PairCloud(points, pixels, angles, (a, b))


def test_other_pairs_confirm_the_wall_and_contradict_the_floaters():
    rng = np.random.default_rng(0)
    cameras = [_camera(x) for x in (0.0, 0.5, 1.0, 1.5, 2.0)]
    noise = 0.01  # 1 cm along the ray: the depth noise of a 0.1 px match at 5 m, ~5.7 degrees
    # 500 floaters where the other pairs' first views see the wall behind them (the right of view 0)
    floater = rng.choice(np.flatnonzero(np.arange(WIDTH * HEIGHT) % WIDTH >= 100), 500, replace=False)
    clouds = [_pair_cloud(cameras, 0, 1, rng, noise, floater)]
    clouds += [_pair_cloud(cameras, k, k + 1, rng, noise) for k in range(1, 4)]
    sizes = [(WIDTH, HEIGHT)] * len(cameras)
    checks = check_views(clouds, cameras, sizes, noise_px=0.3, sigmas=3.0, lookup_px=1)
    n0 = len(clouds[0].points)
    wall = np.setdiff1d(np.arange(n0), floater)
    # where pair 1 and pair 2 see the wall too (x < 1 m: the others' first views overlap it),
    # the wall is confirmed; the floaters never
    seen_by_three = wall[(clouds[0].points[wall, 0] > -1.0) & (clouds[0].points[wall, 0] < 1.4)]
    assert np.mean(checks.support[seen_by_three] >= 3) > 0.97
    assert checks.support[floater].max() == 2 and np.mean(checks.violate[floater] >= 1) > 0.9
    assert checks.confidence[floater].max() < 0.5 < checks.confidence[seen_by_three].min()
    # the agreeing points averaged: nearer the wall than the pair's own
    assert np.std(checks.points[seen_by_three, 2] - 5.0) < 0.75 * np.std(clouds[0].points[seen_by_three, 2] - 5.0)
    # the widest angle: between the rays of the farthest agreeing views
    full = seen_by_three[checks.support[seen_by_three] == 5][:50]
    X = checks.points[full]
    c0, c4 = np.array([0.0, 0, 0]), np.array([2.0, 0, 0])
    r0, r4 = c0 - X, c4 - X
    expected = np.degrees(np.arccos(np.einsum("ij,ij->i", r0, r4) / np.linalg.norm(r0, axis=1) / np.linalg.norm(r4, axis=1)))
    np.testing.assert_allclose(checks.angle[full], expected, atol=1e-9)


def test_a_point_behind_the_others_surface_is_not_contradicted():
    """Hidden from another pair's view (behind what it sees) is no evidence against a point."""
    rng = np.random.default_rng(1)
    cameras = [_camera(x) for x in (0.0, 0.5, 1.0)]
    near = _pair_cloud(cameras, 1, 2, rng, 0.0)
    far = _pair_cloud(cameras, 0, 1, rng, 0.0)
    far = PairCloud(far.points * 2.0, far.pixels, far.angles, far.views)  # z = 10: behind the wall
    checks = check_views([far, near], cameras, [(WIDTH, HEIGHT)] * 3, 0.3, 3.0, 1)
    assert checks.violate[:len(far.points)].max() == 0 and checks.agree[:len(far.points)].max() == 0


def test_depth_sigma_is_the_two_view_formula():
    pts = np.array([[0.0, 0.0, 10.0]])
    assert depth_sigma(pts, np.zeros(3), 1000.0, np.array([30.0]), 0.5)[0] == pytest.approx(10 * 0.5 / (1000 * 0.5))
    P = normalize_projection(-3.0 * _camera(0.0))  # any scale and sign: the depth is the third row's
    assert (P @ [0.0, 0.0, 4.0, 1.0])[2] == pytest.approx(4.0)


def test_dense_config_refuses_a_support_without_a_check():
    with pytest.raises(ValueError, match="min_support"):
        DenseConfig(min_support=1)
    with pytest.raises(ValueError, match="min_confidence"):
        DenseConfig(min_confidence=1.0)
    with pytest.raises(ValueError, match="match_noise_px"):
        DenseConfig(match_noise_px=0.0)


def test_dense_resolution_propagates_on_smaller_images(box_scene, tmp_path, monkeypatch):
    """--dense-resolution: the pairs propagated on images brought down to 320 px (half the
    render's 640): a quarter of the pixels, the same surface, the cameras and seeds in the
    resized frame (a slip of the pixel map would put the points off the surface)."""
    from stereoseed.config import Config
    from stereoseed.dense.densify import densify
    from stereoseed.dense.frames import dense_scale
    from stereoseed.experiments.evaluation import TrueCorrespondences, surface_distance
    from stereoseed.pipeline import reconstruct

    import tempfile

    from stereoseed.dense import densify as dense_module

    scene = box_scene.prefix(3)
    cfg = Config()
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], cfg, source=TrueCorrespondences(scene))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    spools = []
    monkeypatch.setattr(dense_module, "PairSpool", lambda folder: spools.append(folder) or PairSpool(folder))
    full, full_report = densify(recon, cfg)
    assert len(spools) == 1 and spools[0].startswith(str(tmp_path)) and not list(tmp_path.iterdir())  # spool gone
    half, report = densify(recon, cfg.replace(dense={"resolution": 320}))
    assert dense_scale(recon.views[0].image_size, 320) == 0.5 and report["resolution_scale"] == 0.5
    assert report["fusion_voxel_m"] == pytest.approx(2 * full_report["fusion_voxel_m"])
    assert 0.15 < report["points_before_fusion"] / full_report["points_before_fusion"] < 0.35
    d_full, d_half = surface_distance(full.points), surface_distance(half.points)
    assert np.median(d_half) < 2.5 * np.median(d_full) and np.median(d_half) < 0.001  # half the pixels' precision
    assert report["peak_memory_mb"]["process"] > 0
    assert "resolution_lowered" not in report
    # the same pairs held within a budget of pixels: brought down alike, and said
    budget, budget_report = densify(recon, cfg.replace(dense={"max_megapixels": 2 * 0.08}))
    assert budget_report["resolution_scale"] == pytest.approx(0.5, abs=0.01)
    assert "max_megapixels" in budget_report["resolution_lowered"]
    assert np.median(surface_distance(budget.points)) < 0.001
    with pytest.raises(ValueError, match="resolution"):
        DenseConfig(resolution=-1)
    with pytest.raises(ValueError, match="max_megapixels"):
        DenseConfig(max_megapixels=float("nan"))


def test_the_pixel_budget_lowers_the_resolution_only_when_exceeded():
    """The fountain's 10 pairs at 3072 x 2048 (63 MP) fit the default budget as they are; 39
    pairs of 6000 x 4000 photos are brought down to the largest side within it."""
    from types import SimpleNamespace

    from stereoseed.dense.frames import budgeted_resolution, dense_scale

    def walk(n, size):
        return [SimpleNamespace(image_size=size) for _ in range(n)], [(i, i + 1) for i in range(n - 1)]

    budget = DenseConfig().max_megapixels
    assert budgeted_resolution(*walk(11, (3072, 2048)), 0, budget) == 0
    assert budgeted_resolution(*walk(11, (3072, 2048)), 1000, budget) == 1000  # asked for less: kept
    views, pairs = walk(40, (6000, 4000))
    side = budgeted_resolution(views, pairs, 0, budget)

    def megapixels(side):
        s = dense_scale((6000, 4000), side)
        return len(pairs) * round(6000 * s) * round(4000 * s) / 1e6

    assert megapixels(side) <= budget < megapixels(side + 1)
    assert 1500 < side < 1700
    assert budgeted_resolution(views, pairs, 0, 0.0) == 0  # no limit


@pytest.mark.parametrize("options, says", [(["--min-support", "1"], "DenseConfig.min_support must be a whole number >= 2"),
                                           (["--dense-resolution", "-5"], "DenseConfig.resolution must be a whole number >= 0")])
def test_dense_options_out_of_range_are_one_line_before_any_work(options, says, tmp_path, capsys):
    from stereoseed.cli import main

    out = tmp_path / "out"
    assert main(["reconstruct", str(tmp_path), "--calib", str(tmp_path / "c.json"), "--out", str(out), "--dense",
                 *options]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and not out.exists()


def test_max_points_grows_the_voxel_until_the_cloud_fits(box_scene):
    from stereoseed.config import Config
    from stereoseed.dense.densify import densify
    from stereoseed.experiments.evaluation import TrueCorrespondences, surface_distance
    from stereoseed.pipeline import reconstruct

    scene = box_scene.prefix(3)
    cfg = Config()
    recon, _ = reconstruct(scene.images, scene.names, scene.P[:2], cfg, source=TrueCorrespondences(scene))
    full, full_report = densify(recon, cfg)
    limit = len(full) // 5
    small, report = densify(recon, cfg.replace(dense={"max_points": limit}))
    # within the limit, not far below it (the voxel grown by the square root of the excess)
    assert 0.7 * limit < len(small) <= limit
    assert report["fusion_voxel_m"] > 2 * full_report["fusion_voxel_m"]
    assert np.median(surface_distance(small.points)) < 0.001


def test_a_pair_is_checked_against_the_pairs_that_overlap_it_most():
    """DenseConfig.check_pairs: beyond that many pairs, each pair's points are checked against
    the pairs whose first views share the most sparse points with its own (ascending, so that
    the merge adds them in the order every pair would), never one that shares none."""
    from stereoseed.dense.fusion import every_other_pair, overlapping_pairs

    assert every_other_pair(3).tolist() == [[1, 2], [0, 2], [0, 1]]
    shared = np.array([[50, 9, 3, 0, 7],
                       [9, 50, 8, 2, 0],
                       [3, 8, 50, 6, 1],
                       [0, 2, 6, 50, 5],
                       [7, 0, 1, 5, 50]])
    assert overlapping_pairs(shared, 4).tolist() == every_other_pair(5).tolist()  # a walk within the limit
    assert overlapping_pairs(shared, 0).tolist() == every_other_pair(5).tolist()  # 0: every pair
    assert overlapping_pairs(shared, 2).tolist() == [[1, 4], [0, 2], [1, 3], [2, 4], [0, 3]]
    lonely = shared.copy()
    lonely[0, 1:] = lonely[1:, 0] = 0
    lonely[0, 2] = lonely[2, 0] = 1
    assert overlapping_pairs(lonely, 2)[0].tolist() == [2, -1]  # none that shares nothing


def test_a_rig_walks_pairs_that_share_a_first_view_are_each_checked():
    """A rig walk pairs each station's two images and then the station with the next: two pairs
    start from the same view, and both must be checked against their neighbours (the shared
    points are counted per distinct view, then given to each pair)."""
    from stereoseed.dense.densify import pair_overlaps
    from stereoseed.dense.fusion import overlapping_pairs

    from stereoseed.scene.reconstruction import Reconstruction

    class Model:  # what Reconstruction.shared_points reads: views, observations, points, live points
        views = [None] * 6
        obs_view = np.array([0, 1, 2, 0, 2, 4, 2, 4, 5])
        obs_point = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
        points = np.zeros((3, 3))
        alive = np.array([True, True, True])
        shared_points = Reconstruction.shared_points

    pairs = [(0, 1), (0, 2), (2, 3), (2, 4), (4, 5)]
    shared = pair_overlaps(Model(), pairs)
    assert shared.tolist() == [[2, 2, 2, 2, 1], [2, 2, 2, 2, 1], [2, 2, 3, 3, 2], [2, 2, 3, 3, 2], [1, 1, 2, 2, 2]]
    others = overlapping_pairs(shared, 2)
    assert (others >= 0).sum(axis=1).tolist() == [2, 2, 2, 2, 2]  # every pair checked, the station pairs too


def test_the_spool_gives_the_pairs_stacked_as_in_memory(tmp_path):
    """The pairs' clouds kept on disk until the fusion come back as the in-memory stack, colours
    in step."""
    from stereoseed.dense.fusion import PairClouds, PairSpool

    rng = np.random.default_rng(3)
    cameras = [_camera(x) for x in (0.0, 0.3, 0.6)]
    clouds = [_pair_cloud(cameras, a, a + 1, rng, 0.01) for a in (0, 1)]
    clouds.append(PairCloud(np.zeros((0, 3)), np.zeros((0, 2), np.int64), np.zeros(0), (2, 0)))  # a pair with none
    colors = [rng.integers(0, 256, (len(c.points), 3), dtype=np.uint8) for c in clouds]
    spool = PairSpool(tmp_path)
    for cloud, col in zip(clouds, colors):
        spool.add(cloud, col)
    stacked = spool.stacked()
    expected = PairClouds.stack(clouds)
    for name in ("points", "pixels", "angles", "offsets", "views"):
        np.testing.assert_array_equal(getattr(stacked, name), getattr(expected, name))
        assert getattr(stacked, name).dtype == getattr(expected, name).dtype
    for q, col in enumerate(colors):
        np.testing.assert_array_equal(spool.colors(q), col)
