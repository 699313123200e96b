"""End-to-end incremental reconstruction against the synthetic ground truth (issues 4 and 7)."""
import json

import cv2
import numpy as np
import pytest

from stereoseed.geometry.projection import camera_center, decompose_projection, project
from stereoseed.config import Config, PipelineConfig, ResectionConfig
from stereoseed.experiments.evaluation import (TrueCorrespondences, camera_errors, corners_from_exact_pixels,
                                  reconstruct_corners, rms_3d)
from stereoseed.io.ply import read_ply
from stereoseed.pipeline import as_finished, reconstruct, save_outputs
from stereoseed.estimators.resection import implausible_intrinsics
from stereoseed.synthetic.scene import SceneConfig, render_scene


def _run(scene, mode, source=None, **pipeline):
    cfg = Config(pipeline=PipelineConfig(mode=mode, **pipeline))
    return reconstruct(scene.images, scene.names, scene.P[:2], cfg, source=source)


def _centre_errors(recon, scene):
    return np.array(camera_errors([v.P for v in recon.views], scene.P)["center_m"][2:], dtype=float)


def _corner_rms(recon, scene):
    X, seen = reconstruct_corners([v.P for v in recon.views], [v.features for v in recon.views], scene.corners,
                                  scene.P, [scene.corner_visibility(i) for i in range(scene.n_images)])
    return rms_3d(X, scene.corners[seen]), len(seen)


def _corner_rms_with_true_cameras(recon, scene):
    X, seen = reconstruct_corners(list(scene.P), [v.features for v in recon.views], scene.corners, scene.P,
                                  [scene.corner_visibility(i) for i in range(scene.n_images)])
    return rms_3d(X, scene.corners[seen])


def oracle_limit(scene, mode="paper"):
    """The chain's own drift: the same pipeline fed with exact correspondences (+0.1 px noise,
    300 matches per pair). Returns per-image centre errors (m) of images 2..n-1."""
    recon, _ = _run(scene, mode, TrueCorrespondences(scene, noise_px=0.1, max_matches=300))
    return _centre_errors(recon, scene)


@pytest.fixture(scope="module")
def paper_oracle(box_scene):
    return oracle_limit(box_scene, "paper")


def test_paper_chain_with_exact_matches_drifts_within_the_known_limit(paper_oracle):
    assert np.all(np.isfinite(paper_oracle))
    assert paper_oracle.max() < 0.012  # the issue measured 0.1-1.2 cm on this ring
    assert paper_oracle.max() > paper_oracle[0]  # it drifts: errors compound along the chain


def test_accurate_mode_beats_the_paper_chain_on_exact_matches(box_scene, paper_oracle):
    accurate = oracle_limit(box_scene, "accurate")
    assert accurate.mean() * 5 <= paper_oracle.mean()
    assert accurate.mean() < 0.0015


@pytest.mark.parametrize("mode", ["paper", "accurate"])
def test_real_matching_stays_near_the_exact_match_limit(box_scene, paper_oracle, mode):
    recon, report = _run(box_scene, mode)
    errors = _centre_errors(recon, box_scene)
    assert report["registered"] == box_scene.n_images, report["per_image"]
    # image by image, within 1.5x the drift envelope of the exact-match paper chain so far
    envelope = np.maximum.accumulate(paper_oracle)
    assert np.all(errors <= 1.5 * envelope + 1e-4), (errors, envelope)
    rms, n = _corner_rms(recon, box_scene)
    assert n >= 150
    # The corners are triangulated from their Harris detections, which on this scene sit 0.3 px
    # (median) from the truth: that alone gives ~1.4 mm with the *true* cameras. The estimated
    # cameras add little to it (measured: accurate 1.00x, paper 1.25x).
    detector_limit = _corner_rms_with_true_cameras(recon, box_scene)
    assert rms < (1.1 if mode == "accurate" else 1.35) * detector_limit, (rms, detector_limit)
    # the corners from their exact pixels: what the cameras alone cost (measured: paper 0.51 mm,
    # accurate 0.05 mm)
    X, seen = corners_from_exact_pixels([v.P for v in recon.views], box_scene.corners, box_scene.P,
                                        [box_scene.corner_visibility(i) for i in range(box_scene.n_images)])
    assert len(seen) == len(box_scene.corners)
    exact_pixels = rms_3d(X, box_scene.corners[seen])
    if mode == "accurate":
        # measured 0.24 mm mean, 0.58 mm max (the paper's chain: 1.7 mm mean)
        assert errors.mean() < 0.0006, errors
        assert exact_pixels < 0.0002, exact_pixels
    else:
        assert exact_pixels < 0.0012, exact_pixels
    assert report["reprojection"]["rms_px"] < 0.5
    assert "no_zoom" not in report["final"]  # this camera zooms by up to 10 % at every image


def test_noisy_images_register_every_camera(box_scene_noisy):
    recon, report = _run(box_scene_noisy, "accurate")
    assert report["registered"] == box_scene_noisy.n_images
    assert _centre_errors(recon, box_scene_noisy).mean() < 0.0008  # measured 0.32 mm


def test_a_final_global_adjustment_removes_the_drift_of_an_open_ring():
    # scene seed 1, sigma 2: the windowed chain drifts along the optical axes (focal lengths
    # 0.01 % -> 0.14 % short from image 2 to 13, centres 0.2 -> 1.3 mm off); the accurate
    # mode's final global BA takes it out (measured mean 0.92 -> 0.28 mm)
    # ba="local" differs from "final" in the finishing step alone: one run gives both, the local
    # one as it would finish after the last image (pipeline.as_finished)
    scene = render_scene(SceneConfig(noise_sigma=2.0, seed=1))
    local_cfg = Config(pipeline=PipelineConfig(mode="accurate", ba="local"))
    drifted = []

    def finish_locally(recon, per_image):
        if len(per_image) == scene.n_images:
            with as_finished(recon, local_cfg) as (local, local_report):
                assert "final_ba" not in local_report["final"]
                drifted.extend(_centre_errors(local, scene))

    final, report = reconstruct(scene.images, scene.names, scene.P[:2], Config(pipeline=PipelineConfig(mode="accurate")),
                                after_insertion=finish_locally)
    assert not report["final"]["loop_closure"]["closed"]  # an open ring: the final BA is its own
    assert report["ba"] == "final" and report["final"]["final_ba"]["free_cameras"] == scene.n_images - 2
    drifted, adjusted = np.array(drifted), _centre_errors(final, scene)
    assert drifted[-1] > 2 * drifted[0], drifted
    assert adjusted.mean() < 0.5 * drifted.mean() and adjusted.mean() < 0.0005, (adjusted, drifted)


def test_plain_box_without_epipolar_geometry_is_placed_by_the_motion_prior(plain_box_scene):
    # No robust F exists between these views (repeated squares on flat faces): the constant-motion
    # prior, a robust similarity and the three-view check place the first insertions.
    scene = plain_box_scene
    cfg = Config(pipeline=PipelineConfig(mode="accurate"))
    recon, report = reconstruct(scene.images[:6], scene.names[:6], scene.P[:2], cfg)
    assert report["registered"] == 6, [r.get("reason") for r in report["per_image"]]
    assert all("motion_prior_correspondences" in r for r in report["per_image"][2:])
    errors = np.array(camera_errors([v.P for v in recon.views], scene.P[:6])["center_m"][2:], dtype=float)
    # ~100 corners on two flat faces leave the focal length weakly observed (this scene zooms by
    # up to 10 % at every image, and resection prefers "no zoom" unless the data pay for it):
    # the centres slide along the optical axis by up to ~2.5 cm at 1.4 m (textured box: < 0.1 cm),
    # far less than the 10 cm period of the squares a wrong match would cost
    assert errors.max() < 0.03, errors


def test_plain_box_hypotheses_reach_past_the_three_best_pairings():
    # Found on scene seed 3: the last image saw few squares; every hypothesis drawn from each
    # point's 3 best pairings was 8-29 cm off (the true camera would explain 51 recent points,
    # the chosen one 36) and the image landed 11 cm off; hypotheses from the 6 best pairings too:
    # 2.5 cm. Since the analytic-Jacobian refinement seed 3 no longer needs the wider search;
    # seed 1 does (twice), which the assertion below checks.
    scene = render_scene(SceneConfig(textured=False, seed=1))
    recon, report = _run(scene, "accurate")
    assert report["registered"] == scene.n_images
    searches = [r["motion_prior_search"] for r in report["per_image"][2:] if "motion_prior_search" in r]
    assert any(s["pairings_per_point"] == 6 for s in searches), searches  # the scenario happened
    errors = _centre_errors(recon, scene)
    assert errors.max() < 0.04, errors


def test_a_lens_that_does_not_zoom_is_best_held_fixed():
    # squares only and no zoom: a free focal length per image trades against the depth (few
    # points, narrow view); the calibrated intrinsics held fixed remove that (measured mean
    # centre error 0.79 -> 0.19 cm over 8 images), whether the user says so (camera_model
    # "fixed") or no resection found a zoom (the accurate mode's final BA then holds them)
    scene = render_scene(SceneConfig(textured=False, focal_jitter=0.0, n_images=8))
    focal, _ = _run(scene, "accurate", hold_unzoomed=False)
    fixed, report = _run(scene, "accurate", camera_model="fixed")
    held, report_held = _run(scene, "accurate")
    assert report["camera_model"] == "fixed" and report["registered"] == scene.n_images
    assert report_held["final"]["no_zoom"] and not any(r["resection_model"] == "focal" for r in report_held["per_image"][2:])
    for recon in (fixed, held):
        Ks = [decompose_projection(v.P)[0] for v in recon.views[2:]]
        np.testing.assert_allclose(Ks, [decompose_projection(recon.views[1].P)[0]] * len(Ks), atol=1e-6)
        assert _centre_errors(recon, scene).mean() < 0.5 * _centre_errors(focal, scene).mean()
        assert _centre_errors(recon, scene).mean() < 0.004


def test_noisy_plain_box_registers_every_image(plain_box_scene_noisy):
    # sigma 2, squares only: an earlier version slipped by one period here (corners 5.8 cm off)
    # when the motion prediction missed the squares by 55 px; the wide search that fixed it is
    # tested on its own in sfm/test_mapper.py (this rendering no longer needs it: each image is
    # placed by the near search)
    scene = plain_box_scene_noisy
    recon, report = _run(scene, "accurate")
    assert report["registered"] == scene.n_images, [r.get("reason") for r in report["per_image"]]
    assert all(r["registered_by"] == "motion prior" for r in report["per_image"][2:])
    rms, n = _corner_rms(recon, scene)
    assert rms < 0.005, rms
    assert _centre_errors(recon, scene).mean() < 0.04


def test_paper_mode_on_the_plain_box_refuses_ill_conditioned_11_dof_cameras(plain_box_scene):
    # 60-200 corners of repeated squares on two faces: the best 11-DOF camera can sit 76 cm
    # away with a third of the focal length (or the principal point 200 px off) and still
    # reproject them within 0.3 px. Such cameras are refused and the view takes the focal-only
    # model; before, the chain stopped after 4 of 14 images.
    recon, report = _run(plain_box_scene, "paper")
    assert report["registered"] == plain_box_scene.n_images, [r.get("reason") for r in report["per_image"]]
    refused = [r for r in report["per_image"][2:] if "free_camera_refused" in r]
    assert refused and all("implausible" in r["free_camera_refused"] or "ill-conditioned" in r["free_camera_refused"]
                           for r in refused)
    assert all(r["resection_model"] in ("focal", "fixed") for r in refused)
    ref_K = decompose_projection(plain_box_scene.P[1])[0]
    twice_the_bounds = ResectionConfig(max_principal_point_shift=0.2, max_aspect_change=0.06, max_skew=0.02)
    for v in recon.views[2:]:
        if v.camera_model is None:  # kept its 11-DOF camera: a physical one (the BA may nudge it)
            assert implausible_intrinsics(v.P, ref_K, (640, 480), twice_the_bounds) is None, v.name
    # the two-view chain on ~60 points per pair still drifts: measured 0.3-2.6 cm over the first
    # five insertions, up to 7.6 cm after (the accurate mode: 0.9 cm mean)
    assert _centre_errors(recon, plain_box_scene)[:5].max() < 0.05


def test_a_robust_f_locked_on_repeated_squares_is_overruled_by_the_motion_prior():
    # In this rendering the robust F between images 10 and 11 fits 21 matches of squares shifted
    # by one period (a camera 17 cm off); the weak chain is checked against the motion prior and
    # the camera explaining the most points wins.
    scene = render_scene(SceneConfig(textured=False, seed=2))
    recon, report = _run(scene, "accurate")
    assert report["registered"] == scene.n_images, [r.get("reason") for r in report["per_image"]]
    overruled = [r for r in report["per_image"][2:] if r["matches"] > 0 and "motion_prior_correspondences" in r]
    assert overruled, "no weak epipolar chain was checked"
    assert _centre_errors(recon, scene).max() < 0.02


def test_plain_box_squares_only_registers_every_camera(plain_box_scene):
    # Over ten renderings (seeds 0-4, sigma 0 and 2) every camera is registered; in nine the mean
    # centre error is 0.3-1.1 cm, in one the last image is 10 cm off. This rendering: corners
    # 0.60 mm.
    recon, report = _run(plain_box_scene, "accurate")
    assert report["registered"] == plain_box_scene.n_images, [r.get("reason") for r in report["per_image"]]
    rms, n = _corner_rms(recon, plain_box_scene)
    assert n >= 200
    assert rms < 0.0015, rms


def test_a_bad_image_is_reported_and_skipped(box_scene, tmp_path):
    images = list(box_scene.images[:6])
    names = list(box_scene.names[:6])
    images.insert(4, np.full_like(images[0], 128))  # a blank frame in the middle of the walk
    names.insert(4, "blank.png")
    cfg = Config()
    recon, report = reconstruct(images, names, box_scene.P[:2], cfg)
    statuses = {r["image"]: r["status"] for r in report["per_image"]}
    assert statuses["blank.png"] == "failed"
    assert "blank.png" in next(r["reason"] for r in report["per_image"] if r["image"] == "blank.png")
    assert report["registered"] == 6  # the next image is placed from the last registered ones
    save_outputs(recon, report, tmp_path)
    cams = json.loads((tmp_path / "cameras.json").read_text())["images"]
    assert [c["name"] for c in cams] == names
    blank = next(c for c in cams if c["name"] == "blank.png")
    assert blank["registered"] is False and "P" not in blank
    good = next(c for c in cams if c["name"] == names[5])
    truth = box_scene.P[4]
    assert np.linalg.norm(np.array(good["center"]) - (-np.linalg.inv(truth[:, :3]) @ truth[:, 3])) < 0.01
    pts, cols = read_ply(tmp_path / "sparse.ply")
    assert len(pts) == report["points"] and cols.dtype == np.uint8
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["mode"] == "accurate" and rep["camera_model"] == "focal" and rep["window"] == 3
    assert rep["ba"] == "final" and not rep["final"]["loop_closure"]["closed"]
    assert rep["final"]["final_ba"]["free_cameras"] == report["registered"] - 2


def test_temple_ring_registers_every_image_near_the_true_cameras(temple_run):
    recon, report, truth = temple_run
    assert report["registered"] == len(truth), [r.get("reason") for r in report["per_image"]]
    errors = camera_errors([v.P_input for v in recon.views], truth)
    centre = np.array(errors["center_m"][2:], dtype=float)
    rotation = np.array(errors["rotation_deg"][2:], dtype=float)
    # measured: median 1.0 mm, worst 3.0 mm, rotations <= 0.4 deg; RANSAC seeds 0-2: median
    # 1.01 / 1.01 / 0.99 mm. The camera is ~0.6 m away with a 1520 px focal length: depth and
    # focal length are hard to tell apart (a free focal length per image: median 2.3 mm, worst
    # 7.7 mm); no resection found a zoom, so the final BA held the calibrated intrinsics. The
    # turned views need the reference principal point in their frame.
    assert report["final"]["no_zoom"]
    assert np.median(centre) < 0.002, centre  # issue 7: 5 mm
    assert centre.max() < 0.006, centre
    assert rotation.max() < 1.0, rotation
    # three images were taken upside down relative to their predecessor: found and exported
    # in the input image's frame (checked by the centre errors above)
    assert sum(bool(v.rotated_180) for v in recon.views) >= 1


def test_corners_from_exact_pixels_with_the_true_cameras_are_exact(box_scene):
    vis = [box_scene.corner_visibility(i) for i in range(box_scene.n_images)]
    X, seen = corners_from_exact_pixels(list(box_scene.P), box_scene.corners, box_scene.P, vis)
    assert len(seen) == len(box_scene.corners)
    assert rms_3d(X, box_scene.corners[seen]) < 1e-9
    # an unregistered image (None) is left out; a corner seen by one camera only is not a point
    Ps = [box_scene.P[0], None, box_scene.P[2]] + [None] * (box_scene.n_images - 3)
    X, seen = corners_from_exact_pixels(Ps, box_scene.corners, box_scene.P, vis)
    assert np.array_equal(seen, np.flatnonzero(vis[0] & vis[2]))


def test_a_camera_that_jumped_farther_than_the_object_is_refused(box_scene):
    from stereoseed.scene.reconstruction import View
    from stereoseed.sfm.registration.base import implausible_motion

    points = box_scene.corners  # ~1.4 m in front of every camera of the ring
    previous = View("prev", P=box_scene.P[1])
    P2, P6 = box_scene.P[2], box_scene.P[6]  # 20 and 100 degrees further
    assert implausible_motion(P2, previous, points, 1, 1.5) is None  # a 20-degree step: ~0.5 m
    assert "moved" in implausible_motion(P6, previous, points, 1, 1.5)  # ~2 m in one step
    assert implausible_motion(P6, previous, points, 5, 1.5) is None  # unless images were skipped in between
    K, R, t = box_scene.K[2], box_scene.R[2], box_scene.t[2]
    zoomed = np.diag([2.0, 2.0, 1.0]) @ K @ np.hstack([R, t[:, None]])
    assert "focal length" in implausible_motion(zoomed, previous, points, 1, 1.5)
    assert implausible_motion(zoomed, previous, points, 1, 2.5) is None


def test_global_adjust_leaves_a_lone_pair_alone():
    # nothing registered past the calibrated pair: no BA, so no residual to call an outlier
    from geometry_helpers import box_points, ring_camera
    from stereoseed.features.harris import Features
    from stereoseed.sfm.refinement import global_adjust
    from stereoseed.scene.reconstruction import Reconstruction, View

    rng = np.random.default_rng(6)
    X = box_points(rng, 100)
    views = []
    for i, a in enumerate((0.0, 10.0)):
        P = ring_camera(a)[3]
        x = project(P, X)
        x[:5] += 15.0  # gross errors a BA would expose
        feats = Features(x, np.zeros((len(X), 1), np.float32), np.ones(len(X), bool), np.ones(len(X)), (480, 640))
        views.append(View(name=f"v{i}", features=feats, point_of_feature=np.full(len(X), -1, np.int64)))
    recon = Reconstruction(views)
    for i in range(2):
        recon.calibrate(i, ring_camera((0.0, 10.0)[i])[3])
    ids = recon.add_points(X, np.zeros((len(X), 3)))
    for i in range(2):
        recon.add_observations(i, np.arange(len(X)), ids)
    opts = Config(pipeline=PipelineConfig(mode="accurate")).mapper_options()
    ba, removed = global_adjust(recon, opts.bundle, opts.outliers, opts.pipeline.camera_model)
    assert ba.get("skipped") and removed == 0
    assert len(recon.obs_point) == 200 and recon.alive.all()


def test_global_adjust_drops_outliers_and_adjusts_again():
    from geometry_helpers import box_points, ring_camera
    from stereoseed.features.harris import Features
    from stereoseed.sfm.refinement import global_adjust
    from stereoseed.scene.reconstruction import Reconstruction, View

    rng = np.random.default_rng(5)
    X = box_points(rng, 300)
    cams = [ring_camera(a)[3] for a in (0.0, 10.0, 30.0, 50.0, 70.0, 90.0)]
    views = []
    for i, P in enumerate(cams):
        x = project(P, X) + rng.normal(0, 0.2, (len(X), 2))
        if i > 1:  # 10 % gross mismatches in the moving camera's images
            x[rng.random(len(X)) < 0.1] += rng.uniform(8, 20, 2) * rng.choice([-1, 1], 2)
        feats = Features(x, np.zeros((len(X), 1), np.float32), np.ones(len(X), bool), np.ones(len(X)), (480, 640))
        views.append(View(name=f"v{i}", features=feats, P=P.copy(), point_of_feature=np.full(len(X), -1, np.int64)))
    recon = Reconstruction(views)
    ids = recon.add_points(X + rng.normal(0, 0.005, X.shape), np.zeros((len(X), 3)))
    for i in range(len(cams)):
        recon.add_observations(i, np.arange(len(X)), ids)
    for v in views[2:]:  # drifted cameras: 1-2 cm off
        v.P = ring_camera(float(np.degrees(np.arctan2(*camera_center(v.P)[1::-1]))) + 0.6, distance=1.41)[3]
    cfg = Config(pipeline=PipelineConfig(mode="accurate"))
    opts = cfg.mapper_options()
    ba, removed = global_adjust(recon, opts.bundle, opts.outliers, opts.pipeline.camera_model)
    assert ba["rounds"] >= 2 and removed > 0
    wrong = np.linalg.norm(recon.observation_xy() - np.concatenate(
        [project(cams[v], X[recon.obs_point[recon.obs_view == v]]) for v in range(len(cams))]), axis=1) > 3
    assert not wrong.any()  # every gross mismatch is gone
    centre = [np.linalg.norm(camera_center(v.P) - camera_center(P)) for v, P in zip(views[2:], cams[2:])]
    # the refit without the mismatches: 0.24 px for 0.2 px noise (one round ends at 3.9 px with
    # the cameras up to 6 mm off, and the mismatches it could not see yet still in)
    assert ba["rms_after_px"] < 0.3 < ba["rms_first_round_before_px"]
    assert max(centre) < 0.005, centre


def _untimed(report):
    if isinstance(report, dict):
        return {k: _untimed(v) for k, v in report.items() if k != "seconds"}
    return [_untimed(v) for v in report] if isinstance(report, list) else report


def _state(recon):
    return [None if v.P is None else v.P.copy() for v in recon.views], recon.live_points()[0].copy()


def test_a_run_as_finished_midway_is_the_run_on_the_images_so_far(box_scene):
    """as_finished after the 4th image gives what a run on those 4 images gives, to the last
    bit (the finishing step: loop closure, global BA), and the run then goes on as if nothing
    happened. The paper bench evaluates every image count of a figure this way."""
    images, names, pair = box_scene.images[:5], box_scene.names[:5], box_scene.P[:2]
    seen = {}

    def after_insertion(recon, per_image):
        if len(per_image) == 4:
            with as_finished(recon, Config()) as (model, report):
                seen["state"], seen["report"] = _state(model), report
            assert len(per_image) == 4 and "final" not in per_image[-1]

    recon5, report5 = reconstruct(images, names, pair, after_insertion=after_insertion)
    recon4, report4 = reconstruct(images[:4], names[:4], pair)
    cams, points = seen["state"]
    assert all(np.array_equal(a, b) for a, b in zip(cams[:4], _state(recon4)[0]))
    assert np.array_equal(points, _state(recon4)[1]) and len(points) > 500
    for key in ("registered", "points", "reprojection", "per_image", "final"):  # the timings aside
        assert _untimed(seen["report"][key]) == _untimed(report4[key]), key
    plain5, _ = reconstruct(images, names, pair)
    cams5, points5 = _state(recon5)
    assert all(np.array_equal(a, b) for a, b in zip(cams5, _state(plain5)[0]))
    assert np.array_equal(points5, _state(plain5)[1])


def test_a_world_frame_far_away_is_moved_next_to_the_cameras_and_back(small_box_scene):
    # UTM-sized coordinates (1e7 m): the run works near the cameras and returns the world frame;
    # the cameras and points are those of the same scene at the origin, moved
    scene = small_box_scene.prefix(5)
    near, _ = reconstruct(scene.images, scene.names, scene.P[:2], Config())
    offset = np.array([4.2e6, 5.3e6, 120.0])
    T = np.eye(4)
    T[:3, 3] = -offset  # world = old + offset: P_far X_far = P (X_far - offset)
    far_pair = [P @ T for P in scene.P[:2]]
    far, report = reconstruct(scene.images, scene.names, far_pair, Config())
    assert report["frame_offset"] is not None and np.linalg.norm(report["frame_offset"]) > 1e6
    for a, b in zip(near.views, far.views):
        assert a.registered == b.registered
        if a.registered:
            np.testing.assert_allclose(camera_center(b.P) - offset, camera_center(a.P), atol=1e-5)
    pa, _ = near.live_points()
    pb, _ = far.live_points()
    np.testing.assert_allclose(pb - offset, pa, atol=1e-5)


def test_a_walk_in_reverse_after_the_pair_is_never_confidently_wrong():
    # the pair, then the walk from its far end back (the first images 100 degrees away): an image
    # is placed right, flagged or refused, never metres off as registered (it once was: 2.5 m)
    scene = render_scene(SceneConfig(n_images=7))
    order = [0, 1, 6, 5, 4, 3, 2]
    recon, report = reconstruct([scene.images[i] for i in order], [scene.names[i] for i in order], scene.P[:2],
                                Config())
    assert report["registered"] >= 5
    for v, i in zip(recon.views[2:], order[2:]):
        if v.registered and v.reliable:
            assert np.linalg.norm(camera_center(v.P_input) - camera_center(scene.P[i])) < 0.01, v.name
