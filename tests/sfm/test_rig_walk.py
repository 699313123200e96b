"""A stereo rig walked with both cameras (issue #38): every station placed, the rig held, metric."""
import copy
import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scene_helpers import write_calib, write_video

from stereoseed.cli import main
from stereoseed.config import Config
from stereoseed.estimators.rig_resection import Rig
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.projection import camera_center
from stereoseed.dense.densify import densify
from stereoseed.experiments.evaluation import surface_distance
from stereoseed.pipeline import reconstruct
from stereoseed.sfm.finishing import judge_cameras as assess
from stereoseed.synthetic.rig import RigConfig, render_rig
from stereoseed.synthetic.scene import SceneConfig
from stereoseed.scene.camera_life import Flag


@pytest.fixture(scope="module")
def rig_scene():
    """Five stations 30 degrees apart (wider than the matcher's search: the walk's motion finds
    them), 320 x 240 images, noise sigma 1."""
    view = replace(SceneConfig(), width=320, height=240, focal_px=400.0, focal0_px=390.0, supersample=1)
    return render_rig(RigConfig(stations=5, noise_sigma=1.0, view=view))


@pytest.fixture(scope="module")
def rig_run(rig_scene):
    s = rig_scene.scene
    return reconstruct(s.images, s.names, s.P[:2], Config(), rig=True)


def test_every_station_is_placed_with_the_calibrated_rig(rig_scene, rig_run):
    recon, report = rig_run
    s = rig_scene.scene
    assert report["registered"] == len(s.images)
    assert all(r.get("registered_by") == "stereo rig" for r in report["per_image"][2:])
    rig = recon.rig
    for st in range(1, rig_scene.stations):
        station = Rig.from_projections(recon.views[2 * st].P, recon.views[2 * st + 1].P)
        np.testing.assert_allclose(station.R_rl, rig.R_rl, atol=1e-9)
        np.testing.assert_allclose(station.t_rl, rig.t_rl, atol=1e-9)
    errors = [np.linalg.norm(camera_center(v.P_input) - camera_center(P)) for v, P in zip(recon.views, s.P)]
    assert max(errors) < 0.006, errors  # metres, 1.4 m away (the single camera at 320 px: 5-10 mm)


def test_the_scale_holds_along_the_walk(rig_scene, rig_run):
    recon, _ = rig_run
    s = rig_scene.scene
    last = len(recon.views) - 2
    est = np.linalg.norm(camera_center(recon.views[last].P_input) - camera_center(recon.views[0].P_input))
    true = np.linalg.norm(camera_center(s.P[last]) - camera_center(s.P[0]))
    assert abs(est / true - 1) < 0.002


def test_each_station_has_one_uncertainty_and_one_flag(rig_scene, rig_run):
    recon, _ = rig_run
    s = rig_scene.scene
    for v in range(2, len(recon.views)):  # the rig held: the right camera is as determined as its left one
        u = recon.views[v].uncertainty
        assert u is not None and u.determined, (v, u and u.reason)
        err = recon.views[v].R @ (camera_center(recon.views[v].P) - camera_center(s.P[v]))
        assert np.all(np.abs(err) < 5 * u.position_sigma + 1e-6), (v, err, u.position_sigma)
    # the station's pose carries both: the right camera's sigma follows the left one's
    left, right = recon.views[4].uncertainty, recon.views[5].uncertainty
    assert np.linalg.norm(left.position_sigma - right.position_sigma) < 0.2 * np.linalg.norm(left.position_sigma)
    # what flags one image of a station flags its partner (one rigid body)
    again = copy.deepcopy(recon)  # the module's run stays as it is
    again.flag(4, Flag.parse("ambiguous: repeated structure (as if)"))
    out = assess(again, Config().replace(trust={"keep_flagged": True}))
    assert set(out["flagged"]) == {s.names[4], s.names[5]}
    assert out["flagged"][s.names[5]].endswith(f"(its station's {s.names[4]})")


def test_dense_takes_each_station_s_own_pair_first_then_across_stations(rig_scene, rig_run):
    recon, _ = rig_run
    names = rig_scene.scene.names
    cloud, report = densify(recon, Config())
    n = rig_scene.stations
    own = [[names[2 * s], names[2 * s + 1]] for s in range(n)]
    across = [[names[2 * s], names[2 * s + 2]] for s in range(n - 1)]
    assert [p["pair"] for p in report["pairs"]] == own + across
    d = surface_distance(cloud.points)
    assert len(cloud) > 100_000 and np.median(d) < 0.002 and np.mean(d < 0.01) > 0.95  # metres (1.6 mm at 320 px)


def _write_rig(rig_scene, folder, stations=None):
    s = rig_scene.scene
    n = rig_scene.stations if stations is None else stations
    for side, name in ((0, "left"), (1, "right")):
        (folder / name).mkdir(parents=True, exist_ok=True)
        for k in range(n):
            cv2.imwrite(str(folder / name / f"{k:03d}.png"), s.images[2 * k + side])
    return folder / "left", folder / "right", write_calib(folder / "calib.json", s.P[:2])


def test_reconstruct_rig_writes_each_image_with_its_station_and_side(rig_scene, tmp_path):
    left, right, calib = _write_rig(rig_scene, tmp_path / "walk", stations=3)
    assert main(["reconstruct", "--rig", str(left), str(right), "--calib", str(calib), "--out",
                 str(tmp_path / "out"), "--quiet"]) == 0
    cams = json.loads((tmp_path / "out" / "cameras.json").read_text())["images"]
    assert [(c["station"], c["side"]) for c in cams] == [(k, side) for k in range(3) for side in ("left", "right")]
    # both sides name their images alike: each name gets its folder's in front
    assert [c["name"] for c in cams[:2]] == ["left_000.png", "right_000.png"]
    assert all(c["registered"] for c in cams)
    # the result records each image's photo, side and own name: the hand-offs find left_000.png's
    inputs = json.loads((tmp_path / "out" / "inputs.json").read_text())["images"]
    assert [(e["name"], e["side"], e["original_name"], e["path"]) for e in inputs[:2]] == [
        ("left_000.png", "left", "000.png", "../walk/left/000.png"),
        ("right_000.png", "right", "000.png", "../walk/right/000.png")]
    assert main(["export", str(tmp_path / "out"), "--format", "nerfstudio", "--out", str(tmp_path / "ns")]) == 0
    frames = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert sorted(f["file_path"] for f in frames) == sorted(f"images/{c['name']}" for c in cams)
    assert (tmp_path / "ns" / "images" / "right_002.png").read_bytes() == (right / "002.png").read_bytes()
    # --images as given to reconstruct --rig: both folders hold a 002.png, the record tells them apart
    assert main(["export", str(tmp_path / "out"), "--format", "nerfstudio", "--images", str(left), str(right),
                 "--out", str(tmp_path / "told")]) == 0
    for c in cams:
        assert (tmp_path / "told" / "images" / c["name"]).read_bytes() == (
            tmp_path / "ns" / "images" / c["name"]).read_bytes()


def test_a_rig_of_unequal_sides_is_refused_in_one_line(rig_scene, tmp_path, capsys):
    left, right, calib = _write_rig(rig_scene, tmp_path / "walk", stations=2)
    (right / "001.png").unlink()
    assert main(["reconstruct", "--rig", str(left), str(right), "--calib", str(calib), "--out",
                 str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2 images" in err[0] and "1" in err[0] and "together" in err[0]
    assert main(["reconstruct", "--rig", str(left), "--calib", str(calib), "--out", str(tmp_path / "out2"),
                 "--quiet"]) == 2
    assert "two image sources" in capsys.readouterr().err


@pytest.fixture(scope="module")
def rig_films(tmp_path_factory):
    """A rig filmed: 30 stations 3 degrees apart as two MJPG videos (left.avi, right.avi) and
    the first station's calibration: (left, right, calib.json, the rendered scene)."""
    view = replace(SceneConfig(), width=320, height=240, focal_px=400.0, focal0_px=390.0, supersample=1,
                   pose_jitter=False)
    scene = render_rig(RigConfig(stations=30, step_deg=3.0, noise_sigma=1.0, view=view)).scene
    folder = tmp_path_factory.mktemp("films")
    write_video(folder / "left.avi", scene.images[0::2])
    write_video(folder / "right.avi", scene.images[1::2])
    return folder / "left.avi", folder / "right.avi", write_calib(folder / "calib.json", scene.P[:2]), scene


def test_a_rig_filmed_on_two_videos_is_walked_from_the_same_frames(rig_films, tmp_path):
    left, right, calib, scene = rig_films
    out = tmp_path / "out"
    assert main(["reconstruct", "--rig", str(left), str(right), "--calib", str(calib), "--out", str(out),
                 "--quiet"]) == 0
    cams = json.loads((out / "cameras.json").read_text())["images"]
    frames = [int(c["name"].split("_")[1].split(".")[0]) for c in cams]
    # the first station is the calibrated first frames; every station's two images one frame
    assert frames[:2] == [0, 0] and frames[0::2] == frames[1::2] and len(cams) >= 6
    assert [c["side"] for c in cams] == ["left", "right"] * (len(cams) // 2)
    assert all(c["registered"] and c["reliable"] for c in cams)
    for c, frame in zip(cams, frames):  # each against the rendered camera of its frame and side
        truth = scene.P[2 * frame + (c["side"] == "right")]
        assert np.linalg.norm(camera_center(np.array(c["P"])) - camera_center(truth)) < 0.006, c["name"]
    assert sorted(p.name for p in (out / "keyframes").iterdir()) == sorted(c["name"] for c in cams)


def test_two_videos_of_unequal_length_or_a_video_beside_images_are_refused(rig_scene, rig_films, tmp_path, capsys):
    left, _, calib, scene = rig_films
    right = write_video(tmp_path / "right.avi", scene.images[1::2][:20])  # the right one cut to 20 frames
    assert main(["reconstruct", "--rig", str(left), str(right), "--calib", str(calib), "--out",
                 str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "30 frames" in err[0] and "20" in err[0] and "together" in err[0]
    images, _, _ = _write_rig(rig_scene, tmp_path / "walk", stations=2)
    assert main(["reconstruct", "--rig", str(left), str(images), "--calib", str(calib), "--out",
                 str(tmp_path / "out2"), "--quiet"]) == 2
    assert "two videos" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out2").exists()


def test_refine_rig_recovers_a_rig_calibrated_slightly_wrong(rig_scene):
    """The pair calibrated with the right camera turned 0.3 degrees off: held, every station
    inherits it; --refine-rig (PipelineConfig.refine_rig) brings the rotation back toward the
    true one, the baseline's length (the scale) kept."""
    from stereoseed.geometry.models import rotation_from_vector

    s = rig_scene.scene
    K, R, t = Camera(s.P[1]).krt
    C = -R.T @ t
    R_wrong = rotation_from_vector(np.radians([0.0, 0.3, 0.0])) @ R
    P_wrong = K @ np.hstack([R_wrong, (-R_wrong @ C)[:, None]])
    true_rig = rig_scene.rig

    def angle_off(rig):
        return np.degrees(np.arccos(np.clip((np.trace(rig.R_rl @ true_rig.R_rl.T) - 1) / 2, -1, 1)))

    held, _ = reconstruct(s.images, s.names, [s.P[0], P_wrong], Config(), rig=True)
    refined, report = reconstruct(s.images, s.names, [s.P[0], P_wrong],
                                  Config().replace(pipeline={"refine_rig": True}), rig=True)
    assert angle_off(held.rig) == pytest.approx(0.3, abs=1e-6)
    assert angle_off(refined.rig) < 0.1
    assert refined.rig.baseline == pytest.approx(held.rig.baseline, rel=1e-12)


def test_report_html_draws_the_rig_of_each_station(rig_scene, tmp_path):
    from stereoseed.pipeline import save_outputs

    s = rig_scene.scene
    recon, report = reconstruct(s.images[:6], s.names[:6], s.P[:2], Config(), rig=True)
    save_outputs(recon, report, tmp_path, Config())
    page = (tmp_path / "report.html").read_text()
    assert "stereo rig (each station)" in page
    from stereoseed.output.report.figures import RIG_COLOUR
    from stereoseed.output.report.measure import SCALE_COLOUR

    assert RIG_COLOUR in page and SCALE_COLOUR in page and RIG_COLOUR != SCALE_COLOUR  # told apart


def test_rig_videos_named_alike_get_their_side_in_front(rig_films, tmp_path):
    import shutil

    from stereoseed.io.video import read_rig_keyframes

    left, right, _, _ = rig_films
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    # one file on a case-insensitive file system
    shutil.copy(left, tmp_path / "a" / "Walk.avi")
    shutil.copy(right, tmp_path / "b" / "walk.avi")
    lefts, rights = read_rig_keyframes(tmp_path / "a" / "Walk.avi", tmp_path / "b" / "walk.avi")
    assert all(k.name.startswith("left_Walk_") for k in lefts) and all(k.name.startswith("right_walk_") for k in rights)
    assert [k.index for k in lefts] == [k.index for k in rights] and lefts[0].index == 0
