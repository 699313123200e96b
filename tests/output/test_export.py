"""The result folder and its exports, checked with the field's readers as oracles: pycolmap
reads the COLMAP model (text and binary), plyfile every PLY."""
import json

import numpy as np
import pytest

from stereoseed.geometry.projection import camera_center
from stereoseed.cli import main
from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_calibration
from stereoseed.io.ply import read_ply_vertices
from stereoseed.pipeline import reconstruct, save_outputs
from stereoseed.output.reader import load_result
from stereoseed.output.results import FORMAT_VERSION, exported_points

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) is the COLMAP oracle")


@pytest.fixture(scope="module")
def box_result(box_scene, tmp_path_factory):
    """The 14-image box ring reconstructed (accurate mode) and saved: (recon, report, folder)."""
    recon, report = reconstruct(box_scene.images, box_scene.names, box_scene.P[:2], Config())
    out = tmp_path_factory.mktemp("box_result")
    save_outputs(recon, report, out)
    return recon, report, out


def test_the_result_folder_keeps_every_observation(box_result):
    recon, report, out = box_result
    result = load_result(out)
    tr = result.tracks
    assert int(tr["format_version"]) == FORMAT_VERSION
    cams = json.loads((out / "cameras.json").read_text())
    assert cams["format_version"] == FORMAT_VERSION and cams["images"][0]["width"] == 640
    assert json.loads((out / "report.json").read_text())["format_version"] == FORMAT_VERSION
    # every observation of the live points is there, at the pixel the run used
    live = recon.alive & (recon.track_lengths() >= 2)
    assert len(tr["point_xyz"]) == live.sum() and len(tr["obs_point"]) == np.isin(recon.obs_point, np.flatnonzero(live)).sum()
    for i in (0, 5, 13):
        here = tr["obs_image"] == i
        xy = result.keypoints(i)[tr["obs_keypoint"][here]]
        X = tr["point_xyz"][tr["obs_point"][here]]
        h = X @ result.P[i][:, :3].T + result.P[i][:, 3]
        assert np.max(np.linalg.norm(h[:, :2] / h[:, 2:] - xy, axis=1)) < 4 * np.median(tr["point_error"]) + 1.0
    # each keypoint of an image belongs to at most one point
    for i in result.registered:
        keys = tr["obs_keypoint"][tr["obs_image"] == i]
        assert len(np.unique(keys)) == len(keys)


def test_the_plys_carry_their_attributes(box_result):
    recon, report, out = box_result
    tr = load_result(out).tracks
    sparse = read_ply_vertices(out / "sparse.ply")
    assert {"x", "red", "error", "track_length", "n_views"} <= set(sparse.dtype.names)
    np.testing.assert_allclose(sparse["error"], tr["point_error"], rtol=1e-6)
    assert np.array_equal(sparse["track_length"], np.bincount(tr["obs_point"]))
    assert sparse["n_views"].min() >= 2 and np.all(sparse["n_views"] <= sparse["track_length"])
    from plyfile import PlyData

    frustums = PlyData.read(str(out / "cameras.ply"))
    assert len(frustums["vertex"].data) == 5 * report["registered"] and len(frustums["face"].data) == 4 * report["registered"]
    apex = np.stack([frustums["vertex"].data[c] for c in "xyz"], axis=1)[::5]  # each frustum's first vertex
    truth = np.array([recon.views[v].center for v in recon.registered_views])
    assert np.max(np.linalg.norm(apex - truth, axis=1)) < 1e-5  # float32 in the file


def test_far_points_are_left_out_of_the_exports(box_result):
    recon, _, _ = box_result
    factor = Config().export.far_point_factor
    kept = exported_points(recon, factor)
    assert len(kept) == np.sum(recon.alive & (recon.track_lengths() >= 2))  # nothing is far on the box
    saved = recon.checkpoint()
    try:
        recon.points[kept[0]] = [90.0, 0.0, 0.0]  # the temple once had a point 94 m off a 10 cm object
        assert kept[0] not in exported_points(recon, factor) and len(exported_points(recon, factor)) == len(kept) - 1
    finally:
        recon.restore(saved)


@pytest.mark.parametrize("binary", [False, True])
def test_pycolmap_reads_the_colmap_export(box_result, tmp_path, binary):
    recon, report, out = box_result
    result = load_result(out)
    args = ["export", str(out), "--format", "colmap", "--out", str(tmp_path)] + (["--binary"] if binary else [])
    assert main(args) == 0
    model = pycolmap.Reconstruction(str(tmp_path))
    assert sorted(im.name for im in model.images.values()) == sorted(result.names[i] for i in result.registered)
    for im in model.images.values():
        C = camera_center(result.P[result.names.index(im.name)])
        assert np.linalg.norm(np.asarray(im.projection_center()) - C) <= 1e-9 * np.linalg.norm(C)
    assert len(model.points3D) == len(result.tracks["point_xyz"])
    assert sum(p.track.length() for p in model.points3D.values()) == len(result.tracks["obs_point"])
    stored = model.compute_mean_reprojection_error()
    model.update_point_3d_errors()  # COLMAP recomputes them with its own pixel convention
    assert abs(model.compute_mean_reprojection_error() - stored) < 0.01
    assert abs(stored - result.tracks["point_error"].mean()) < 1e-9


def test_colmaps_bundle_adjustment_finds_the_model_at_its_optimum(box_result, tmp_path):
    _, _, out = box_result
    main(["export", str(out), "--out", str(tmp_path)])
    model = pycolmap.Reconstruction(str(tmp_path))
    before = {im.name: np.asarray(im.projection_center()) for im in model.images.values()}
    names = load_result(out).names
    config = pycolmap.BundleAdjustmentConfig()
    for im in model.images.values():
        config.add_image(im.image_id)
        config.set_constant_cam_intrinsics(im.camera_id)
        if im.name in names[:2]:  # the calibrated pair fixes the frame and the scale, as in our BA
            config.set_constant_rig_from_world_pose(im.frame_id)
    pycolmap.create_default_bundle_adjuster(pycolmap.BundleAdjustmentOptions(), config, model).solve()
    distance = np.median([np.linalg.norm(C) for C in before.values()])
    moved = max(np.linalg.norm(np.asarray(im.projection_center()) - before[im.name]) for im in model.images.values())
    assert moved < 1e-4 * distance, moved / distance  # measured 1e-5


def test_a_colmap_model_calibrates_a_new_run(box_result, box_scene, tmp_path):
    _, _, out = box_result
    main(["export", str(out), "--out", str(tmp_path / "colmap")])
    main(["export", str(out), "--out", str(tmp_path / "colmap_bin"), "--binary"])
    result = load_result(out)
    for folder in ("colmap", "colmap_bin"):
        P1, P2 = read_calibration(tmp_path / folder, box_scene.names[:2])
        for P, truth in ((P1, result.P[0]), (P2, result.P[1])):
            np.testing.assert_allclose(P / np.linalg.norm(P[2, :3]), truth / np.linalg.norm(truth[2, :3]), atol=1e-9)
    with pytest.raises(StereoseedError, match="no camera for image"):
        read_calibration(tmp_path / "colmap", ["elsewhere.png", box_scene.names[1]])
    (tmp_path / "empty").mkdir()
    with pytest.raises(StereoseedError, match="not a COLMAP model"):
        read_calibration(tmp_path / "empty", box_scene.names[:2])


def test_nvm_and_bundler_exports_hold_every_camera_and_point(box_result, tmp_path):
    _, report, out = box_result
    result = load_result(out)
    assert main(["export", str(out), "--format", "nvm", "--out", str(tmp_path)]) == 0
    lines = (tmp_path / "model.nvm").read_text().splitlines()
    n_cams = int(lines[2])
    assert lines[0] == "NVM_V3" and n_cams == report["registered"]
    assert int(lines[3 + n_cams]) == len(result.tracks["point_xyz"])
    name, f, qw, qx, qy, qz, cx, cy, cz = lines[3].split()[:9]
    np.testing.assert_allclose([float(cx), float(cy), float(cz)], camera_center(result.P[0]), atol=1e-9)
    assert main(["export", str(out), "--format", "bundler", "--out", str(tmp_path)]) == 0
    head = (tmp_path / "bundle.out").read_text().splitlines()[1].split()
    assert [int(v) for v in head] == [report["registered"], len(result.tracks["point_xyz"])]
    assert (tmp_path / "list.txt").read_text().split() == [result.names[i] for i in result.registered]


def test_export_of_a_folder_without_a_result_is_one_line(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "no cameras.json" in capsys.readouterr().err
