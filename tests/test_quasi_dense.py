"""Quasi-dense registration of weakly textured views (stereoseed.quasi_dense_registration)."""
from __future__ import annotations

import numpy as np
import pytest

from stereoseed import mapper
from stereoseed.config import Config
from stereoseed.evaluation import camera_errors
from stereoseed.io import read_middlebury_par
from stereoseed.pipeline import load_sequence, reconstruct
from stereoseed.quasi_dense_registration import QUASI_DENSE, grid_best, reconsider, weak_chain_limit
from stereoseed.registration import RegistrationFailure, register_view
from stereoseed.synthetic import SceneConfig, render_scene


def test_grid_best_keeps_the_best_match_of_each_cell():
    xy = np.array([[1.0, 1.0], [6.0, 2.0], [9.0, 1.0], [12.0, 3.0], [3.0, 9.0]])
    scores = np.array([0.6, 0.9, 0.7, 0.8, 0.5])
    rows = grid_best(xy, scores, 8)
    assert sorted(rows.tolist()) == [1, 3, 4]  # cells (0,0): 0.9 beats 0.6; (1,0): 0.8 beats 0.7


def test_weak_chain_limit_follows_the_trusted_chain():
    cfg = Config()
    assert weak_chain_limit(cfg) == 2 * cfg.resection.min_inliers  # MotionPriorConfig.trusted_chain_factor 2
    assert weak_chain_limit(cfg.replace(quasi_dense={"weak_chain_inliers": 40})) == 40


@pytest.fixture(scope="module")
def faint_scene():
    """The box ring with a faint texture (albedo standard deviation 0.02 instead of 0.10)."""
    return render_scene(SceneConfig(n_images=6, texture_amplitude=0.02))


def test_faint_texture_registers_every_image_and_quasi_dense_where_the_chain_is_weak(faint_scene):
    scene = faint_scene
    recon, report = reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert report["registered"] == scene.config.n_images
    per = report["per_image"][2:]
    limit = weak_chain_limit(Config())
    for r in per:  # the path follows the rule: quasi-dense only after a weak sparse chain
        assert (r["registered_by"] == QUASI_DENSE) == ("sparse_weak" in r and "quasi_dense_failed" not in r
                                                       and r["resection_inliers"] >= limit)
    assert any(r["registered_by"] == QUASI_DENSE for r in per)
    err = camera_errors([v.P_input for v in recon.views], scene.P)["center_m"][2:]
    assert np.median(err) < 0.003 and max(err) < 0.01  # metres, against the rendered cameras


def test_reconsider_changes_nothing(faint_scene):
    scene = faint_scene
    cfg = Config().resolved()
    recon, _ = mapper.initialise(scene.images, scene.names, scene.P[:2], cfg)
    before = recon.checkpoint()
    found = reconsider(recon, 2, register_view(recon, 2, cfg), cfg)
    after = recon.checkpoint()
    assert np.array_equal(before.points, after.points)
    assert all(np.array_equal(a, b) for a, b in zip(before.observations, after.observations))
    for a, b in zip(before.views, after.views):  # cameras, interest points (by reference), links
        assert (a[0] is None and b[0] is None) or np.array_equal(a[0], b[0])
        assert a[1] is b[1] and np.array_equal(a[2], b[2])
    assert not isinstance(found, RegistrationFailure)


def test_dino_weak_views_registered_by_quasi_dense(dino_dir):
    """dinoSparseRing, the first eight images of the walk: the sparse path alone registers 3 of
    the 6 after the pair (the third 24 mm off); with the quasi-dense path all 6 register."""
    images, names, P_pair = load_sequence(str(dino_dir / "ring_order.txt"), str(dino_dir / "dinoSR_par.txt"))
    truth = read_middlebury_par(dino_dir / "dinoSR_par.txt")
    n = 8
    recon, report = reconstruct(images[:n], names[:n], P_pair, Config())
    assert report["registered"] == n
    paths = [r["registered_by"] for r in report["per_image"][2:]]
    assert paths.count(QUASI_DENSE) >= 3
    err = np.array(camera_errors([v.P_input for v in recon.views], [truth[m] for m in names[:n]])["center_m"][2:])
    # metres; measured 0.4, 15, 71, 14, 68, 77 mm (images 2-7), and 0.7, 14, 66, 119, 52, 38 mm
    # after the analytic-Jacobian resection: registered, not yet accurate, the worst camera
    # moving with small changes upstream (COLMAP 4.2 on the whole ring: 4 of 14 images, 32 mm
    # median). What holds: the median, and every camera but the worst within 10 cm.
    assert np.median(err) < 0.05 and np.sort(err)[-2] < 0.1
