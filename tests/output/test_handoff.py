"""The hand-offs to Gaussian-splatting and nerfstudio, on a ring shot through a lens and
reconstructed with it: pycolmap reads the undistorted workspace, OpenCV's undistortPoints and a
render of the same scene without the lens are the oracles of the undistortion, plyfile reads
the cloud."""
import hashlib
import json
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from stereoseed.cli import main
from stereoseed.errors import StereoseedError
from stereoseed.geometry.lens import distort_pixels
from stereoseed.geometry.projection import project
from stereoseed.output.handoff import (
    HandoffConfig,
    undistorted_frame,
    undistortion_maps_to,
    write_colmap_undistorted,
    write_nerfstudio,
)
from stereoseed.output.reader import load_result
from stereoseed.pipeline import reconstruct_to_folder
from stereoseed.synthetic.scene import SceneConfig, render_scene, write_scene

from geometry_helpers import opencv_undistort_points

pycolmap = pytest.importorskip("pycolmap", reason="pycolmap (the test extra) is the COLMAP oracle")

LENS = (-0.12, 0.03, 0.001, -0.0005)  # barrel, with tangential terms
# the moving camera keeps camera 1's intrinsics, as the lens it is undistorted through assumes
SCENE = SceneConfig(width=320, height=240, focal_px=400.0, focal0_px=390.0, supersample=1, n_images=6,
                    focal_jitter=0.0, distortion=LENS)


@pytest.fixture(scope="module")
def lens_run(tmp_path_factory):
    """The ring photographed through the lens, the pair calibrated with it (its true cameras and
    the lens in calib.json) and reconstructed: (scene, images.txt, result folder)."""
    scene = render_scene(SCENE)
    root = tmp_path_factory.mktemp("lens_run")
    written = write_scene(scene, root / "scene")
    cams = [{"P": scene.P[i].tolist(), "K": scene.K[i].tolist(), "distortion": list(LENS),
             "image_size": [SCENE.width, SCENE.height]} for i in (0, 1)]
    (root / "calib.json").write_text(json.dumps({"cameras": cams}))
    report = reconstruct_to_folder(str(written["images_txt"]), str(root / "calib.json"), root / "result")
    assert report["registered"] == SCENE.n_images
    return scene, written["images_txt"], root / "result"


@pytest.fixture(scope="module")
def workspace(lens_run, tmp_path_factory):
    """The COLMAP hand-off (text model) of the lens run: (folder, what it wrote)."""
    _, images_txt, result = lens_run
    out = tmp_path_factory.mktemp("workspace")
    return out, write_colmap_undistorted(load_result(result), out, [images_txt])


def _centres(result_folder):
    return {im["name"]: np.array(im["center"]) for im in json.loads((result_folder / "cameras.json").read_text())["images"]
            if im["registered"]}


def _to_camera(image, X):
    T = image.cam_from_world().matrix()
    return X @ T[:, :3].T + T[:, 3]


def test_the_undistorted_workspace_is_pinhole_with_the_cameras_of_the_result(lens_run, workspace):
    _, _, folder = lens_run
    out, done = workspace
    result = load_result(folder)
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {c.model.name for c in model.cameras.values()} == {"PINHOLE"}
    assert len(model.cameras) == done.cameras == 2  # camera 0, and camera 1 whose intrinsics the walk held
    assert sorted(im.name for im in model.images.values()) == sorted(result.names) and done.undistorted
    centres = _centres(folder)
    for im in model.images.values():
        C = centres[im.name]
        assert np.linalg.norm(np.asarray(im.projection_center()) - C) <= 1e-6 * np.linalg.norm(C)
        cam = model.cameras[im.camera_id]
        photo = cv2.imread(str(out / "images" / im.name))
        assert photo.shape[1::-1] == (cam.width, cam.height)
        border = np.concatenate([photo[0], photo[-1], photo[:, 0], photo[:, -1]])
        assert np.all(border.max(axis=1) > 0), im.name  # no blank pixel left by the undistortion
    assert len(model.points3D) == len(result.tracks["point_xyz"])
    # the 3D points reproject through the PINHOLE cameras onto the moved observations, each with
    # the error it had in the run (the same ray, the same focal length)
    for im in model.images.values():
        i = result.names.index(im.name)
        cam = model.cameras[im.camera_id]
        seen = [(p.xy, model.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        xy, X = np.array([s[0] for s in seen]), np.array([s[1] for s in seen])
        here = result.tracks["obs_image"] == i
        kp = result.keypoints(i)[result.tracks["obs_keypoint"][here]]
        run_error = np.sort(np.linalg.norm(project(result.P[i], result.tracks["point_xyz"][result.tracks["obs_point"][here]])
                                           - kp, axis=1))
        error = np.sort(np.linalg.norm(cam.img_from_cam(_to_camera(im, X)) - xy, axis=1))
        assert len(error) == here.sum() > 20
        np.testing.assert_allclose(error, run_error, atol=1e-6)


def test_the_pinhole_cameras_see_the_true_corners_where_opencv_undistorts_them(lens_run, workspace):
    """The box's square corners, known in 3D, seen in each photo (through the lens) and
    undistorted by OpenCV onto each PINHOLE camera: the pair, calibrated with the truth, to
    1e-6 px; the walk, whose poses the run estimated, to a fraction of a pixel."""
    scene, _, _ = lens_run
    out, _ = workspace
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-15)
    for im in model.images.values():
        i = scene.names.index(im.name)
        cam = model.cameras[im.camera_id]
        X = scene.corners[scene.corner_visibility(i)]
        K = cam.calibration_matrix() - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # COLMAP's pixel corner
        expected = opencv_undistort_points(scene.project(i, X), scene.K[i], LENS, K, criteria) + 0.5
        moved = np.max(np.linalg.norm(cam.img_from_cam(_to_camera(im, X)) - expected, axis=1))
        assert len(X) > 20 and moved < (1e-6 if i < 2 else 0.25), (im.name, moved)  # measured 2e-13 and 0.06


def test_the_undistorted_photos_are_what_a_pinhole_camera_sees(lens_run, workspace):
    """The pair's undistorted photos against the same scene rendered without the lens (shifted
    to the new principal point): closer than a half-pixel shift of the truth or the photo as
    taken (both blurred a little: the renders are one sample per pixel)."""
    scene, _, _ = lens_run
    out, _ = workspace
    pinhole = render_scene(replace(SCENE, n_images=2, distortion=()))
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    by_name = {im.name: model.cameras[im.camera_id] for im in model.images.values()}
    for i in (0, 1):
        cam = by_name[scene.names[i]]
        undistorted = cv2.imread(str(out / "images" / scene.names[i])).astype(np.float32)
        right = _difference(undistorted, pinhole.images[i], cam, pinhole.K[i])
        assert right < 1.5, right  # measured 0.98, 0.93 grey levels
        assert right < 0.6 * _difference(undistorted, pinhole.images[i], cam, pinhole.K[i], 0.5), right  # measured 2.2
        assert right < 0.6 * _difference(undistorted, scene.images[i], cam, pinhole.K[i]), right  # measured 3.0, 2.8


def _difference(undistorted, image, cam, K, shift_x=0.0):
    """Mean difference (grey levels) of the undistorted photo and ``image`` (of the pinhole
    camera K) moved to the PINHOLE camera's principal point (plus shift_x), both blurred."""
    dx = cam.principal_point_x - 0.5 - K[0, 2] + shift_x
    dy = cam.principal_point_y - 0.5 - K[1, 2]
    seen = cv2.warpAffine(image.astype(np.float32), np.array([[1.0, 0, dx], [0, 1.0, dy]]), (cam.width, cam.height),
                          flags=cv2.INTER_LINEAR, borderValue=(-1, -1, -1))
    inside = cv2.erode(np.all(seen >= 0, axis=2).astype(np.uint8), np.ones((9, 9))).astype(bool)
    return float(np.abs(cv2.GaussianBlur(undistorted, (0, 0), 1.5) - cv2.GaussianBlur(seen, (0, 0), 1.5))[inside].mean())


@pytest.mark.parametrize("lens", [LENS, (0.25, 0.0, 0.0, 0.0), (-0.3, 0.08, 0.0, 0.0), (0.05, 0.0, 0.004, -0.003)],
                         ids=["barrel", "pincushion", "strong-barrel", "tangential"])
def test_the_frame_is_the_largest_without_blank_pixels(lens):
    K_P = np.array([[400.0, 0.0, 158.0], [0.0, 402.0, 121.0], [0.0, 0.0, 1.0]])
    K_L = np.array([[399.0, 0.0, 159.5], [0.0, 401.0, 119.5], [0.0, 0.0, 1.0]])  # the lens's K need not be K_P
    d = np.array([*lens, 0.0])
    size = (320, 240)
    K, (W, H), note = undistorted_frame(K_P, K_L, d, size)
    assert note is None and K[0, 1] == 0 and (K[0, 0], K[1, 1]) == (K_P[0, 0], K_P[1, 1])
    mx, my = undistortion_maps_to(K, (W, H), K_P, K_L, d)
    assert mx.shape == (H, W)
    assert mx.min() >= -1e-3 and mx.max() <= size[0] - 1 + 1e-3 and my.min() >= -1e-3 and my.max() <= size[1] - 1 + 1e-3
    assert (W > size[0]) == (lens[0] < 0)  # a barrel lens gives a larger image, a pincushion one a smaller
    # OpenCV's map is the model's: pixel q samples K_L distort(K_L^-1 K_P K^-1 q)
    q = np.array([[0, 0], [W - 1, H - 1], [W // 3, H // 2], [W - 1, 7]], dtype=np.float64)
    ray = np.column_stack([q, np.ones(len(q))]) @ np.linalg.inv(K).T @ K_P.T
    src = distort_pixels(ray[:, :2] / ray[:, 2:], K_L, d)
    rows, cols = q[:, 1].astype(int), q[:, 0].astype(int)
    np.testing.assert_allclose(np.column_stack([mx[rows, cols], my[rows, cols]]), src, atol=2e-3)
    # two more pixels across (the centre kept) would sample outside the photo in x or in y
    for grow in ((2, 0), (0, 2)):
        K2 = K.copy()
        K2[0, 2] += grow[0] / 2
        K2[1, 2] += grow[1] / 2
        mx2, my2 = undistortion_maps_to(K2, (W + grow[0], H + grow[1]), K_P, K_L, d)
        assert (mx2.min() < -1e-3 or mx2.max() > size[0] - 1 + 1e-3 or my2.min() < -1e-3
                or my2.max() > size[1] - 1 + 1e-3), grow


def test_a_lens_that_leaves_too_little_is_said():
    K = np.array([[200.0, 0.0, 159.5], [0.0, 200.0, 119.5], [0.0, 0.0, 1.0]])
    d = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
    _, size, note = undistorted_frame(K, K, d, (320, 240), HandoffConfig(min_scale=0.95))
    assert size == (304, 228) and "black borders" in note


def test_nerfstudio_gets_the_cameras_the_images_and_the_cloud(lens_run, workspace, tmp_path):
    _, images_txt, folder = lens_run
    result = load_result(folder)
    done = write_nerfstudio(result, tmp_path, [images_txt])
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert meta["camera_model"] == "PINHOLE" and "fl_x" not in meta  # two cameras: intrinsics per frame
    assert len(meta["frames"]) == done.images == len(result.names)
    centres = _centres(folder)
    colmap = pycolmap.Reconstruction(str(workspace[0] / "sparse" / "0"))
    colmap_images = {im.name: im for im in colmap.images.values()}
    flip = np.diag([1.0, -1.0, -1.0])
    for frame in meta["frames"]:
        name = frame["file_path"].removeprefix("images/")
        c2w = np.array(frame["transform_matrix"])
        assert np.linalg.norm(c2w[:3, 3] - centres[name]) <= 1e-6 * np.linalg.norm(centres[name])
        image = cv2.imread(str(tmp_path / frame["file_path"]))
        assert image.shape[1::-1] == (frame["w"], frame["h"])
        # a COLMAP observation, cast through nerfstudio's camera (OpenGL axes, pixel centres at +0.5)
        im = colmap_images[name]
        seen = [(p.xy, colmap.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        xy, X = np.array([s[0] for s in seen]), np.array([s[1] for s in seen])
        cam = np.linalg.inv(c2w) @ np.column_stack([X, np.ones(len(X))]).T
        u = frame["fl_x"] * cam[0] / -cam[2] + frame["cx"]
        v = -frame["fl_y"] * cam[1] / -cam[2] + frame["cy"]
        model_xy = colmap.cameras[im.camera_id].img_from_cam(_to_camera(im, X))
        np.testing.assert_allclose(np.column_stack([u, v]), model_xy, atol=1e-6)
        assert np.median(np.linalg.norm(model_xy - xy, axis=1)) < 0.5
        # the camera looks down its -z, its y up: R^T with the y and z columns turned
        np.testing.assert_allclose(c2w[:3, :3] @ flip, np.asarray(im.cam_from_world().rotation.matrix()).T, atol=1e-9)
    ply = PlyData.read(str(tmp_path / meta["ply_file_path"]))["vertex"]
    xyz = np.column_stack([ply["x"], ply["y"], ply["z"]])
    np.testing.assert_allclose(xyz, result.tracks["point_xyz"], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(np.column_stack([ply["red"], ply["green"], ply["blue"]]), result.tracks["point_rgb"])


def _without_image(result, k):
    """The result with image k's observations gone (as the run leaves a flagged camera's)."""
    keep = result.tracks["obs_image"] != k
    tracks = dict(result.tracks, **{a: result.tracks[a][keep] for a in ("obs_point", "obs_image", "obs_keypoint")})
    return replace(result, tracks=tracks)


def test_frames_of_one_camera_share_their_intrinsics_at_the_top(lens_run, tmp_path):
    _, images_txt, folder = lens_run
    result = load_result(folder)
    walk = replace(_without_image(result, 0), P=[None] + result.P[1:])
    write_nerfstudio(walk, tmp_path, [images_txt])
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert {k: type(meta[k]) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")} == {
        "fl_x": float, "fl_y": float, "cx": float, "cy": float, "w": int, "h": int}
    assert meta["fl_x"] == pytest.approx(400.0, abs=1e-9)
    assert len(meta["frames"]) == 5 and not any("fl_x" in f for f in meta["frames"])


def test_a_result_without_a_lens_hands_off_its_photos_unchanged(lens_run, tmp_path):
    _, images_txt, folder = lens_run
    result = load_result(folder)
    plain = replace(result, distortion=[None] * len(result.names))
    done = write_colmap_undistorted(plain, tmp_path, [images_txt], binary=True)
    assert not done.undistorted
    model = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    photos = images_txt.parent
    for im in model.images.values():
        assert (tmp_path / "images" / im.name).read_bytes() == (photos / im.name).read_bytes()
        i = result.names.index(im.name)
        K = result.P[i][:, :3] @ np.linalg.inv(_rotation(model, im))
        K /= K[2, 2]
        cam = model.cameras[im.camera_id]
        assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == result.sizes[i]
        np.testing.assert_allclose(cam.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], atol=1e-9)
        xy = np.array([p.xy for p in im.points2D])
        np.testing.assert_allclose(xy, result.keypoints(i) + 0.5, atol=1e-12)


def _rotation(model, im):
    return np.asarray(im.cam_from_world().rotation.matrix())


def test_a_flagged_camera_is_handed_off_only_when_the_run_kept_it(lens_run, tmp_path):
    _, images_txt, folder = lens_run
    result = load_result(folder)
    flags = list(result.flags)
    flags[3] = "uncertain: 1-sigma position 0.02 (test)"
    kept = replace(result, flags=flags)
    done = write_colmap_undistorted(kept, tmp_path / "kept", [images_txt])
    assert any("img_003.png: flagged" in w and "exported" in w for w in done.warnings)
    assert "img_003.png" in {im.name for im in pycolmap.Reconstruction(str(tmp_path / "kept" / "sparse" / "0")).images.values()}
    left = _without_image(kept, 3)
    done = write_colmap_undistorted(left, tmp_path / "left", [images_txt])
    assert any("img_003.png" in w and "left out" in w for w in done.warnings) and done.images == 5
    model = pycolmap.Reconstruction(str(tmp_path / "left" / "sparse" / "0"))
    assert "img_003.png" not in {im.name for im in model.images.values()}
    assert not (tmp_path / "left" / "images" / "img_003.png").exists()
    write_nerfstudio(left, tmp_path / "ns", [images_txt])
    frames = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert [f["file_path"] for f in frames] == [f"images/{n}" for n in result.names if n != "img_003.png"]


def test_the_hand_offs_refuse_a_folder_of_other_files_and_missing_photos(lens_run, tmp_path):
    scene, images_txt, folder = lens_run
    result = load_result(folder)
    out = tmp_path / "out"
    write_colmap_undistorted(result, out, [images_txt])
    write_colmap_undistorted(result, out, [images_txt], binary=True)  # again into its own folder
    write_nerfstudio(result, out, [images_txt])
    (out / "images" / "mine.jpg").write_bytes(b"not the export's")
    for write in (write_colmap_undistorted, write_nerfstudio):
        with pytest.raises(StereoseedError, match=r"did not write \(images/\).*--force"):
            write(result, out, [images_txt])
    write_nerfstudio(result, out, [images_txt], force=True)
    assert (out / "images" / "mine.jpg").read_bytes() == b"not the export's"
    theirs = tmp_path / "theirs" / "images" / result.names[0]  # an image of the export's names, not its own
    theirs.parent.mkdir(parents=True)
    theirs.write_bytes(b"their image")
    for write in (write_colmap_undistorted, write_nerfstudio):
        with pytest.raises(StereoseedError, match=rf"{result.names[0]}: stereoseed export did not write it"):
            write(result, theirs.parent.parent, [images_txt], force=True)
    assert sorted(p.name for p in theirs.parent.parent.rglob("*")) == ["images", theirs.name]
    assert theirs.read_bytes() == b"their image"
    old = _without_record(folder, tmp_path / "old")  # a result written before runs recorded their inputs
    with pytest.raises(StereoseedError, match="img_000.png .and 5 more.: no such photo.*--images"):
        write_nerfstudio(load_result(old), tmp_path / "none", [])
    small = tmp_path / "small"
    small.mkdir()
    for name, image in zip(scene.names, scene.images):
        cv2.imwrite(str(small / name), image[:200])
    with pytest.raises(StereoseedError, match="320x200 pixels, but .* 320x240"):
        write_colmap_undistorted(result, tmp_path / "wrong", [small])
    assert not (tmp_path / "none").exists() and not (tmp_path / "wrong").exists()
    photos = tmp_path / "ws" / "images"  # the photos where the export would put its images
    photos.mkdir(parents=True)
    for name in scene.names:
        (photos / name).write_bytes((images_txt.parent / name).read_bytes())
    with pytest.raises(StereoseedError, match="would write over the photo it reads"):
        write_nerfstudio(result, photos.parent, [photos], force=True)
    assert all((photos / n).read_bytes() == (images_txt.parent / n).read_bytes() for n in scene.names)


def _without_record(folder, to):
    """A copy of the result ``folder`` at ``to`` as written before runs recorded their inputs."""
    shutil.copytree(folder, to)
    (to / "inputs.json").unlink()
    return to


def test_export_hands_off_from_the_command_line(lens_run, tmp_path, capsys):
    _, images_txt, folder = lens_run
    assert main(["export", str(folder), "--format", "colmap", "--undistort", "--images", str(images_txt),
                 "--out", str(tmp_path / "gs")]) == 0
    said = capsys.readouterr().out
    assert "6 images undistorted" in said and "2 PINHOLE cameras" in said, said
    assert {c.model.name for c in pycolmap.Reconstruction(str(tmp_path / "gs" / "sparse" / "0")).cameras.values()} == {
        "PINHOLE"}
    assert main(["export", str(folder), "--format", "nerfstudio", "--images", str(images_txt.parent),
                 "--out", str(tmp_path / "ns")]) == 0
    assert "transforms.json" in capsys.readouterr().out and (tmp_path / "ns" / "sparse_pc.ply").is_file()
    old = _without_record(folder, tmp_path / "old")
    assert main(["export", str(old), "--format", "nerfstudio", "--out", str(tmp_path / "bare")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "give --images" in err, err
    assert main(["export", str(folder), "--format", "nvm", "--undistort", "--out", str(tmp_path / "x")]) == 2
    assert "--undistort is for --format colmap" in capsys.readouterr().err


def _exif_turned_jpeg(path, image, orientation: int):
    """``image`` as a JPEG whose EXIF orientation tag says to turn it (3: by 180 degrees)."""
    import struct

    tiff = b"II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + bytes(4)
    app1 = b"Exif\x00\x00" + tiff
    jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    path.write_bytes(jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:])
    return path


def test_a_photo_turned_by_its_exif_is_handed_off_as_it_was_read(tmp_path):
    """Issue 48 row 13: stereoseed reads an EXIF-turned photo turned (OpenCV applies the tag),
    but the hand-off copied the raw file: a trainer that ignores EXIF saw it 180 degrees off the
    camera. The turned pixels are written instead; a photo without the tag is copied as it is."""
    from stereoseed.io.files import read_image
    from stereoseed.output.handoff import copy_as_read

    image = np.zeros((30, 40, 3), np.uint8)
    image[:10, :20] = 255  # a bright top-left corner: turned, it is bottom-right
    photo = _exif_turned_jpeg(tmp_path / "turned.jpg", image, 3)
    seen = read_image(photo)
    assert seen[25, 35].min() > 200 and seen[5, 5].max() < 50  # as the run saw it
    copy_as_read(photo, tmp_path / "out.jpg")
    raw = cv2.imdecode(np.fromfile(tmp_path / "out.jpg", np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    assert np.abs(raw.astype(int) - seen).mean() < 2  # what a reader ignoring EXIF sees: the same pixels
    plain = tmp_path / "plain.jpg"
    plain.write_bytes(cv2.imencode(".jpg", image)[1].tobytes())
    copy_as_read(plain, tmp_path / "plain_out.jpg")
    assert (tmp_path / "plain_out.jpg").read_bytes() == plain.read_bytes()


def test_a_result_finds_the_photos_it_read_without_images(lens_run, tmp_path, capsys):
    scene, images_txt, folder = lens_run
    record = json.loads((folder / "inputs.json").read_text())["images"]
    assert [e["name"] for e in record] == scene.names
    for e in record:  # relative to the result folder, with the file as the run read it
        photo = images_txt.parent / e["name"]
        assert e["path"] == f"../scene/{e['name']}" and e["absolute"] == str(photo.resolve())
        assert e["bytes"] == photo.stat().st_size and e["sha256"] == hashlib.sha256(photo.read_bytes()).hexdigest()
    assert main(["export", str(folder), "--undistort", "--out", str(tmp_path / "gs")]) == 0
    assert "6 images undistorted" in capsys.readouterr().out
    assert main(["export", str(folder), "--format", "nerfstudio", "--out", str(tmp_path / "ns")]) == 0
    assert main(["export", str(folder), "--format", "nerfstudio", "--images", str(images_txt),
                 "--out", str(tmp_path / "told")]) == 0
    for name in scene.names:  # the same photos as --images finds
        assert (tmp_path / "ns" / "images" / name).read_bytes() == (tmp_path / "told" / "images" / name).read_bytes()
        assert (tmp_path / "gs" / "images" / name).is_file()


def test_a_moved_result_finds_the_photos_beside_it_and_refuses_a_changed_one(lens_run, tmp_path, capsys):
    scene, images_txt, folder = lens_run
    moved = tmp_path / "moved"
    shutil.copytree(images_txt.parent, moved / "scene")
    shutil.copytree(folder, moved / "result")
    inputs = moved / "result" / "inputs.json"
    record = json.loads(inputs.read_text())
    for e in record["images"]:  # the photos' old place is gone: only the relative path leads to them
        e["absolute"] = str(tmp_path / "gone" / e["name"])
    inputs.write_text(json.dumps(record))
    assert main(["export", str(moved / "result"), "--format", "nerfstudio", "--out", str(tmp_path / "ns")]) == 0
    capsys.readouterr()
    changed = moved / "scene" / scene.names[2]
    image = cv2.imread(str(changed))
    image[0, 0] = 255 - image[0, 0]
    cv2.imwrite(str(changed), image)
    assert main(["export", str(moved / "result"), "--undistort", "--out", str(tmp_path / "gs")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{scene.names[2]}: the photo at {changed} has changed" in err, err
    assert "give --images" in err and not (tmp_path / "gs").exists()
    (moved / "scene" / scene.names[4]).unlink()
    changed.write_bytes((images_txt.parent / scene.names[2]).read_bytes())
    assert main(["export", str(moved / "result"), "--undistort", "--out", str(tmp_path / "gs")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{scene.names[4]}: its photo is not at" in err and "give --images" in err, err
    record["images"][1]["path"] = 7  # not a record stereoseed writes
    inputs.write_text(json.dumps(record))
    assert main(["export", str(moved / "result"), "--undistort", "--out", str(tmp_path / "gs")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "inputs.json: not the record of this result's images" in err, err
    # --images overrides the record
    assert main(["export", str(moved / "result"), "--undistort", "--images", str(images_txt),
                 "--out", str(tmp_path / "gs")]) == 0
