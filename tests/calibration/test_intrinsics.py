"""One camera from views of a flat board (Zhang): the closed form against exact homographies,
the whole `stereoseed intrinsics` against OpenCV's calibrateCamera on the same corners and the
rendered truth; its file read back by `calibrate --intrinsics1/2`; bad intrinsics files refused
in one line."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stereoseed.calibration import poses as rt
from stereoseed.calibration.detection import detect_target
from stereoseed.calibration.intrinsics import homography, pose_from_homography, zhang_intrinsics
from stereoseed.calibration.lens_calibration import read_opencv_camera
from stereoseed.calibration.target import load_target
from stereoseed.cli import main
from stereoseed.synthetic.target import from_boards, render_target

SIZE = (640, 480)
K = np.array([[720.0, 0.0, 331.0], [0.0, 716.0, 236.0], [0.0, 0.0, 1.0]])
LENS = np.array([-0.21, 0.09, 0.0012, -0.0007, 0.0])


def _board_views(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera-from-board poses of a 180 x 140 mm board 380-520 mm away, tilted 15-45 degrees."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        axis = rng.normal(0, 1, 3)
        axis[2] *= 0.3
        angle = np.radians(rng.uniform(15, 45))
        R = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]
        centre = np.array([90.0, 70.0, 0.0])  # the board's middle
        t = np.array([rng.uniform(-60, 60), rng.uniform(-45, 45), rng.uniform(380, 520)]) - R @ centre
        out.append((R, t))
    return out


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A flat ChArUco board (9 x 7 squares of 20 mm, DICT_4X4_50), photographed 9 times through a
    lens, then once more by a second camera for a pair."""
    folder = tmp_path_factory.mktemp("flat")
    spec = {"unit": "mm", "faces": [{"origin": [0.0, 0.0, 0.0], "u_axis": [1.0, 0.0, 0.0], "v_axis": [0.0, 1.0, 0.0],
                                     "board": {"dictionary": "DICT_4X4_50", "squares": [9, 7], "square_px": 20.0,
                                               "marker_px": 15.0, "first_id": 0, "origin_uv": [0.0, 0.0]}}]}
    (folder / "board.json").write_text(json.dumps(spec))
    target = load_target(folder / "board.json")
    texture = from_boards(target, texels_per_square=32)
    views = _board_views(9)
    paths = []
    for i, (R, t) in enumerate(views):
        paths.append(folder / f"view{i}.png")
        cv2.imwrite(str(paths[-1]), render_target(texture, K, R, t, SIZE, LENS, supersample=2, noise_sigma=1.5,
                                                  seed=i, background=110))
    return folder, target, views, paths, texture


def test_the_closed_form_is_exact_on_exact_homographies():
    views = _board_views(5, seed=3)
    grid = np.stack(np.meshgrid(np.arange(0, 181, 20.0), np.arange(0, 141, 20.0)), -1).reshape(-1, 2)
    Hs = []
    for R, t in views:
        x = (np.c_[grid, np.zeros(len(grid))] @ R.T + t) @ K.T
        Hs.append(homography(grid, x[:, :2] / x[:, 2:]))
    np.testing.assert_allclose(zhang_intrinsics(Hs, SIZE), K, rtol=1e-6, atol=1e-6)
    for H, (R, t) in zip(Hs, views):
        Rh, th = pose_from_homography(H, K)
        np.testing.assert_allclose(Rh, R, atol=1e-8)
        np.testing.assert_allclose(th, t, rtol=1e-8)
    # two views only: the principal point is taken at the centre and the focal lengths solved for
    two = zhang_intrinsics(Hs[:2], SIZE)
    assert np.allclose(two[:2, 2], [(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2]) and abs(two[0, 0] / K[0, 0] - 1) < 0.05
    assert homography(grid[:9], grid[:9] * 2) is None  # one row of corners: no homography


def test_intrinsics_from_a_flat_board_against_opencv_and_the_truth(board, tmp_path, capsys):
    folder, target, views, paths, _ = board
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 110, np.uint8))
    out = tmp_path / "camera.yaml"
    assert main(["intrinsics", "--target", str(folder / "board.json"), *map(str, paths), str(blank), "-o", str(out)]) == 0
    printed = capsys.readouterr()
    assert f"{blank}: skipped: no calibration target found" in printed.err and f"wrote {out}" in printed.out
    for p in paths:  # a check image per photo used, named as calibrate names them, and said
        check = tmp_path / f"camera_cam1_{p.stem}.png"
        assert check.is_file() and f"; check {check}" in printed.out
    K_est, lens, size = read_opencv_camera(out)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    rms, per_view = fs.getNode("avg_reprojection_error").real(), fs.getNode("per_view_reprojection_errors").mat()
    names = [fs.getNode("views").at(i).string() for i in range(fs.getNode("views").size())]
    fs.release()
    assert size == SIZE and names == [str(p) for p in paths] and per_view.shape == (9, 1)
    # OpenCV on the very same corners, the same model (k1 k2 p1 p2)
    dets = [detect_target(p, target) for p in paths]
    obj = [np.c_[d.points3d[:, :2], np.zeros(len(d))].astype(np.float32) for d in dets]
    img = [d.pixels.astype(np.float32) for d in dets]
    ocv_rms, K_ocv, d_ocv, *_ = cv2.calibrateCamera(obj, img, SIZE, None, None, flags=cv2.CALIB_FIX_K3)
    assert rms <= 1.01 * ocv_rms  # measured: the same optimum
    np.testing.assert_allclose(K_est, K_ocv, rtol=2e-3, atol=0.5)
    np.testing.assert_allclose(np.diag(K_est)[:2], np.diag(K)[:2], rtol=5e-3)
    assert np.abs(K_est[:2, 2] - K[:2, 2]).max() < 3 and abs(lens[0] - LENS[0]) < 0.02


def test_a_pair_from_one_shot_of_a_flat_board_with_known_intrinsics(board, tmp_path, capsys):
    """Both cameras' intrinsics from their files; one shot of the board each: the pair's P are
    the true poses in the board's frame."""
    folder, target, views, paths, texture = board
    out = tmp_path / "cam.yaml"
    assert main(["intrinsics", "--target", str(folder / "board.json"), *map(str, paths), "-o", str(out)]) == 0
    R1, t1 = views[0]
    R2, t2 = cv2.Rodrigues(np.array([0.0, np.radians(8.0), 0.0]))[0] @ R1, t1 + np.array([-60.0, 0.0, 5.0])
    second = tmp_path / "second.png"
    cv2.imwrite(str(second), render_target(texture, K, R2, t2, SIZE, LENS, supersample=2, noise_sigma=1.5, seed=7,
                                           background=110))
    calib = tmp_path / "calib.json"
    assert main(["calibrate", "--target", str(folder / "board.json"), str(paths[0]), str(second),
                 "--intrinsics1", str(out), "--intrinsics2", str(out), "-o", str(calib)]) == 0
    capsys.readouterr()
    cams = json.loads(calib.read_text())["cameras"]
    for cam, (R, t) in zip(cams, ((R1, t1), (R2, t2))):
        assert cam["intrinsics_given"] and rt.angle_deg(rt.from_rt(np.array(cam["R"]) @ R.T, np.zeros(3))) < 0.1
        assert np.linalg.norm(np.array(cam["t"]) - t) < 0.005 * np.linalg.norm(t)
    # without the files, one view of a flat board does not make a camera
    code = main(["calibrate", "--target", str(folder / "board.json"), str(paths[0]), str(second), "-o", str(calib)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "1 usable view(s) of a flat target" in err and "--intrinsics" in err


@pytest.mark.parametrize("bad", ["nan", "zero", "inf", "unclosed", "random", "png", "empty", "size"])
def test_a_bad_intrinsics_file_is_one_line_naming_it(board, tmp_path, capsys, bad):
    folder, target, views, paths, _ = board
    path = tmp_path / ("cam.xml" if bad == "unclosed" else "cam.yml")
    matrix = "[ 720., 0., 331., 0., 716., 236., 0., 0., 1. ]"
    lens = "[ -0.2, 0.1, 0., 0., 0. ]"
    width = 640
    if bad == "nan":
        matrix = "[ .Nan, 0., 331., 0., 716., 236., 0., 0., 1. ]"
    elif bad == "zero":
        matrix = "[ 0., 0., 0., 0., 0., 0., 0., 0., 0. ]"
    elif bad == "inf":
        lens = "[ -0.2, .Inf, 0., 0., 0. ]"
    elif bad == "size":
        width = 1280
    text = (f"%YAML:1.0\n---\nimage_width: {width}\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n"
            f"   cols: 3\n   dt: d\n   data: {matrix}\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n"
            f"   cols: 5\n   dt: d\n   data: {lens}\n")
    if bad == "unclosed":
        path.write_text('<?xml version="1.0"?>\n<opencv_storage>\n<camera_matrix type_id="opencv-matrix">')
    elif bad == "random":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    elif bad == "png":
        path.write_bytes(paths[0].read_bytes())
    elif bad == "empty":
        path.write_text("")
    else:
        path.write_text(text)
    code = main(["calibrate", "--target", str(folder / "board.json"), str(paths[0]), str(paths[1]),
                 "--intrinsics1", str(path), "--intrinsics2", str(path), "-o", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"stereoseed: error: {path}: ")
    assert "Traceback" not in err and not (tmp_path / "c.json").exists()
