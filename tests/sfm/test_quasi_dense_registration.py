"""Quasi-dense registration of weakly textured views (stereoseed.sfm.registration.quasi_dense)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stereoseed.sfm import mapper
from stereoseed.config import Config, QuasiDenseConfig
from stereoseed.experiments.evaluation import camera_errors
from stereoseed.estimators.rig_resection import Rig
from stereoseed.geometry.camera import Camera
from stereoseed.io.files import read_middlebury_par
from stereoseed.pipeline import load_sequence, reconstruct
from stereoseed.sfm.correspondence import HarrisZncc
from stereoseed.sfm.registration.base import FoundBy
from stereoseed.sfm.registration.ambiguity import judge_ambiguity
from stereoseed.sfm.registration.quasi_dense import grid_best, weak_chain_limit
from stereoseed.sfm.registration.reconsider import reconsider
from stereoseed.sfm.registration.base import RegistrationFailure, register_view
from stereoseed.synthetic.scene import SceneConfig, render_scene
from stereoseed.scene.camera_life import Flag


def test_grid_best_keeps_the_best_match_of_each_cell():
    xy = np.array([[1.0, 1.0], [6.0, 2.0], [9.0, 1.0], [12.0, 3.0], [3.0, 9.0]])
    scores = np.array([0.6, 0.9, 0.7, 0.8, 0.5])
    rows = grid_best(xy, scores, 8)
    assert sorted(rows.tolist()) == [1, 3, 4]  # cells (0,0): 0.9 beats 0.6; (1,0): 0.8 beats 0.7


def test_weak_chain_limit_follows_the_trusted_chain():
    cfg = Config()
    # MotionPriorConfig.trusted_chain_factor 2
    assert weak_chain_limit(cfg.quasi_dense, cfg.motion_prior, cfg.resection) == 2 * cfg.resection.min_inliers
    assert weak_chain_limit(QuasiDenseConfig(weak_chain_inliers=40), cfg.motion_prior, cfg.resection) == 40


@pytest.fixture(scope="module")
def faint_scene():
    """The box ring with a faint texture (albedo standard deviation 0.02 instead of 0.10)."""
    return render_scene(SceneConfig(n_images=6, texture_amplitude=0.02))


def test_faint_texture_registers_every_image_and_quasi_dense_where_the_chain_is_weak(faint_scene):
    scene = faint_scene
    recon, report = reconstruct(scene.images, scene.names, scene.P[:2], Config())
    assert report["registered"] == scene.config.n_images
    per = report["per_image"][2:]
    limit = weak_chain_limit(Config().quasi_dense, Config().motion_prior, Config().resection)
    for r in per:  # the path follows the rule: quasi-dense only after a weak sparse chain
        assert (r["registered_by"] == FoundBy.QUASI_DENSE) == ("sparse_weak" in r and "quasi_dense_failed" not in r
                                                       and r["resection_inliers"] >= limit)
    assert any(r["registered_by"] == FoundBy.QUASI_DENSE for r in per)
    err = camera_errors([v.P_input for v in recon.views], scene.P)["center_m"][2:]
    assert np.median(err) < 0.003 and max(err) < 0.01  # metres, against the rendered cameras


def test_large_photos_are_propagated_brought_down_and_matched_in_their_own_pixels(faint_scene):
    """Photos larger than QuasiDenseConfig.max_side (here the 640 x 480 renders against 480) are
    seeded and propagated brought down: the matches come back in the photos' pixels (the
    quasi-dense camera as accurate as at full size), and the report says the size used."""
    scene = faint_scene
    cfg = Config().replace(quasi_dense={"max_side": 480})
    recon, report = reconstruct(scene.images, scene.names, scene.P[:2], cfg)
    assert report["registered"] == scene.config.n_images
    err = camera_errors([v.P_input for v in recon.views], scene.P)["center_m"]
    by_quasi_dense = [i for i, r in enumerate(report["per_image"]) if r.get("registered_by") == FoundBy.QUASI_DENSE]
    assert by_quasi_dense and all(report["per_image"][i]["quasi_dense"]["brought_down_to"] == [[480, 360]] * 2
                                  for i in by_quasi_dense)
    assert max(err[i] for i in by_quasi_dense) < 0.003 and np.median(err[2:]) < 0.003  # metres


def test_reconsider_changes_nothing(faint_scene):
    scene = faint_scene
    cfg = Config().mapper_options()
    recon, _ = mapper.initialise(scene.images, scene.names, scene.P[:2], cfg)
    before = recon.checkpoint()
    found = reconsider(recon, 2, register_view(recon, 2, cfg.registering, HarrisZncc.of(cfg)), cfg.registering)
    after = recon.checkpoint()
    assert np.array_equal(before.points, after.points)
    assert all(np.array_equal(a, b) for a, b in zip(before.observations, after.observations))
    for a, b in zip(before.views, after.views):  # cameras, interest points (by reference), links
        assert (a[0] is None and b[0] is None) or np.array_equal(a[0], b[0])
        assert a[1] is b[1] and np.array_equal(a[2], b[2])
    assert not isinstance(found, RegistrationFailure)


def _moved(P: np.ndarray, along_x: float) -> np.ndarray:
    """Camera P (3, 4) with its centre moved ``along_x`` along its own x axis (the walk's way)."""
    cam = Camera(P)
    return cam.K @ np.hstack([cam.R, -(cam.R @ (cam.centre + along_x * cam.R[0]))[:, None]])


def test_an_ambiguous_choice_is_lifted_only_when_the_propagated_matches_tell_the_rivals_apart(faint_scene):
    scene = faint_scene
    options = Config().mapper_options()
    recon, _ = mapper.initialise(scene.images, scene.names, scene.P[:2], options)
    cfg = options.registering
    found = register_view(recon, 2, cfg, HarrisZncc.of(options))
    assert not isinstance(found, RegistrationFailure)
    flag = Flag.parse("ambiguous: repeated structure (as if a rival explained nearly as much)")
    # a rival one 'period' (5 cm, 3.5 % of the 1.4 m distance) along the walk: the matches
    # propagated over the whole overlap lie far from its epipolar lines, the flag goes
    period = dataclasses.replace(found, rivals=(_moved(found.P, 0.05),), flag=flag)
    judged = judge_ambiguity(recon, 1, period, cfg)
    assert judged.flag is None and "ambiguity_resolved" in judged.notes
    assert np.array_equal(judged.P, found.P)  # the choice itself never changes
    # a rival 0.1 mm away agrees with them as well as the winner: the flag stays, with the evidence
    twin = dataclasses.replace(found, rivals=(_moved(found.P, 1e-4),), flag=flag)
    judged = judge_ambiguity(recon, 1, twin, cfg)
    assert judged.flag == flag and judged.notes["ambiguity"].startswith("unresolved: the propagated")
    # the matches say how the two cameras stand to each other: a flagged previous view lifts nothing
    recon.flag(1, Flag.parse("ambiguous: repeated structure (the previous one)"))
    judged = judge_ambiguity(recon, 1, period, cfg)
    assert judged.flag == flag and "is flagged itself" in judged.notes["ambiguity"]
    # on a rig, either image of the previous station: its flag sits on the image it was resected from
    recon.lift_flag(1, "as if lifted")
    recon.flag(0, Flag.parse("ambiguous: repeated structure (the station's left image)"))
    recon.rig = Rig.from_projections(recon.views[0].P, recon.views[1].P)
    judged = judge_ambiguity(recon, 1, period, cfg)
    assert judged.flag == flag and f"{recon.views[0].name}, is flagged itself" in judged.notes["ambiguity"]
    no_rivals = dataclasses.replace(period, rivals=())
    assert judge_ambiguity(recon, 1, no_rivals, cfg) is no_rivals  # nothing to judge: as it is


def test_dino_weak_views_registered_by_quasi_dense(dino_dir):
    """dinoSparseRing, the first eight images of the walk: the sparse path alone registers 3 of
    the 6 after the pair (the third 24 mm off); with the quasi-dense path all 6 register."""
    images, names, P_pair = load_sequence(str(dino_dir / "ring_order.txt"), str(dino_dir / "dinoSR_par.txt"))
    truth = read_middlebury_par(dino_dir / "dinoSR_par.txt")
    n = 8
    recon, report = reconstruct(images[:n], names[:n], P_pair, Config())
    assert report["registered"] == n
    paths = [r["registered_by"] for r in report["per_image"][2:]]
    assert paths.count(FoundBy.QUASI_DENSE) >= 3
    err = np.array(camera_errors([v.P_input for v in recon.views], [truth[m] for m in names[:n]])["center_m"][2:])
    # metres; measured 0.4, 0.6, 1.3, 1.5, 2.4, 6.3 mm (images 2-7) since the local BA holds the
    # calibrated intrinsics and the quasi-dense camera zooms only when the propagated matches'
    # epipolar geometry says so (before: 0.7, 14, 66, 119, 52, 38 mm, the focal length drifting)
    assert np.median(err) < 0.005 and err.max() < 0.02


def test_epipolar_agreement_tells_the_true_camera_from_a_moved_one():
    """Matches generated by two known cameras: the true second camera agrees to the floor, one
    moved sideways by 10 % of the baseline does not."""
    from stereoseed.geometry.projection import fundamental_from_projections
    from stereoseed.sfm.registration.quasi_dense import QuasiDenseMatches, epipolar_agreement, robust_f_agreement
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    R = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    C = np.array([1.0, 0.0, 0.2])
    P2 = K @ np.hstack([R, (-R @ C)[:, None]])
    X = np.column_stack([rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300), rng.uniform(3.5, 4.5, 300)])
    proj = lambda P: (lambda h: h[:, :2] / h[:, 2:])(np.column_stack([X, np.ones(len(X))]) @ P.T)
    m = np.hstack([proj(P1), proj(P2) + rng.normal(0, 0.3, (len(X), 2))])
    qd = QuasiDenseMatches(m, np.ones(len(m)), np.zeros((1, 1), np.int32), np.arange(len(m)),
                           fundamental_from_projections(P1, P2), np.ones(len(m), bool))
    moved = K @ np.hstack([R, (-R @ (C + [0.0, 0.1, 0.0]))[:, None]])
    floor = robust_f_agreement(qd)
    assert epipolar_agreement(P1, P2, qd) == pytest.approx(floor)
    assert epipolar_agreement(P1, moved, qd) > 4 * floor


def test_matches_of_photos_brought_down_by_different_ratios_are_in_the_photos_pixels():
    """Two renders brought down to 320 and 256 px (ratios 0.5 and 0.4): the propagated matches
    mapped back lie where the true correspondence is in the photos' own pixels (pixel (0, 0)
    the centre of the top-left pixel at every size: mapping without the half-pixel shift puts
    them 0.78 px off at the median), and the robust F maps with them."""
    from stereoseed.geometry.projection import epipolar_distances
    from stereoseed.geometry.resampling import brought_down, frame_matrix, to_frame
    from stereoseed.sfm.registration import quasi_dense as qdm

    scene = render_scene(SceneConfig(n_images=2))
    cfg = Config()
    (a, ra), (b, rb) = brought_down(scene.images[0], 320), brought_down(scene.images[1], 256)
    np.testing.assert_allclose(frame_matrix(ra) @ [10.0, 20.0, 1.0], [*to_frame([[10.0, 20.0]], ra)[0], 1.0])
    qd = qdm.propagate_pair(a, b, qdm.sift_seeds(a, b, cfg.quasi_dense.sift_ratio), cfg.quasi_dense, cfg.propagation,
                            None, (ra, rb))
    inliers = qd.matches[qd.grid[qd.f_inlier]]
    true_b, evaluable = scene.true_match(0, 1, inliers[:, :2])
    assert evaluable.sum() > 300
    assert np.median(np.linalg.norm(true_b[evaluable] - inliers[evaluable, 2:], axis=1)) < 0.6  # measured 0.44
    assert np.median(epipolar_distances(qd.F, inliers[:, :2], inliers[:, 2:])) < 0.5  # the F of these pixels
    assert np.array_equal(qd.rows_at(inliers[:, :2]), qd.grid[qd.f_inlier])  # back to their rows
