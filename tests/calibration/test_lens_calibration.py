"""The camera and its lens from views of a 3D pattern, against exact synthetic truth and OpenCV."""
import json

import cv2
import numpy as np
import pytest

from geometry_helpers import box_points, look_at_camera
from stereoseed.errors import StereoseedError
from stereoseed.geometry.lens import project_distorted
from stereoseed.calibration.lens_calibration import calibrate_lens, read_lenses, read_opencv_camera

LENS = np.array([-0.12, 0.03, 0.001, -0.0005, 0.0])
SIZE = (640, 480)


def _views(n_views, noise=0.1, seed=0, lens=LENS):
    """Views of a box-shaped pattern (mm) by one camera and lens from around it: [(X, x)], K, poses."""
    rng = np.random.default_rng(seed)
    X = box_points(rng, 150, half=170.0, height=440.0)
    K = look_at_camera((1.0, 0.0, 0.0), f=800.0, pp=(322.0, 238.0))[0]
    views, poses = [], []
    for i in range(n_views):
        a = np.radians(30.0 + 25.0 * i)
        # the first view looks at the pattern; the others put it in a corner of the frame
        aim = [(0.0, 0.0, 200.0), (330.0, 330.0, 420.0), (-330.0, -330.0, -50.0), (330.0, -330.0, -50.0),
               (-330.0, 330.0, 420.0)][i % 5]
        _, R, t, _ = look_at_camera((1400 * np.cos(a), 1400 * np.sin(a), 700.0), target=aim, f=800.0)
        x = project_distorted(K, R, t, lens, X) + rng.normal(0, noise, (len(X), 2))
        inside = np.all((x > 0) & (x < np.array(SIZE) - 1), axis=1)
        views.append((X[inside], x[inside]))
        poses.append((R, t))
    return views, K, poses


def _frame_error(cal, K, lens, R, t):
    """Max pixel error over the whole frame of the calibrated camera + lens for view 0: each
    pixel's true ray, projected by the estimate."""
    u, v = np.meshgrid(np.linspace(0, SIZE[0] - 1, 17), np.linspace(0, SIZE[1] - 1, 13))
    px = np.c_[u.ravel(), v.ravel()]
    # true rays: undistort with OpenCV (the oracle), put points on them at 1.5 m
    rays = cv2.undistortPoints(px.reshape(-1, 1, 2), K, lens).reshape(-1, 2)
    Xc = np.c_[rays, np.ones(len(rays))] * 1500.0
    X = (Xc - t) @ R  # world
    return np.linalg.norm(project_distorted(cal.K, cal.R[0], cal.t[0], cal.distortion, X) - px, axis=1)


def test_the_lens_model_the_calibration_fits_is_opencvs():
    views, K, poses = _views(1, noise=0.0)
    X, x = views[0]
    R, t = poses[0]
    ocv = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, LENS)[0].reshape(-1, 2)
    np.testing.assert_allclose(project_distorted(K, R, t, LENS, X), ocv, atol=1e-9)


@pytest.mark.parametrize("n_lens,known", [(4, False), (5, False), (4, "K"), (5, "skewed K")])
def test_the_analytic_jacobian_is_the_residuals_derivative(n_lens, known):
    """cv2.projectPoints's derivatives, placed in the parameter layout of _unpack (OpenCV's
    missing skew term added), against central differences of the residuals that calibrate_lens
    minimises."""
    from stereoseed.calibration.lens_calibration import _jacobian, _unpack

    views, K, poses = _views(2)
    rng = np.random.default_rng(1)
    K_known = K + np.array([[0, 6.0, 0], [0, 0, 0], [0, 0, 0]]) if known == "skewed K" else K
    fixed = (K_known, LENS) if known else None
    intrinsics = [] if known else [810.0, 790.0, 318.0, 241.0, *(LENS[:n_lens] * 0.8)]
    pose = [v for R, t in poses for v in (*cv2.Rodrigues(R)[0].ravel() + rng.normal(0, 0.01, 3), *t + rng.normal(0, 5, 3))]
    p = np.array(intrinsics + pose)

    def residuals(q):
        Kq, d, Rs, ts = _unpack(q, len(views), n_lens, fixed)
        return np.concatenate([(project_distorted(Kq, R, t, d, X) - x).ravel() for (X, x), R, t in zip(views, Rs, ts)])

    steps = 1e-6 * np.maximum(np.abs(p), 1.0)
    numeric = np.stack([(residuals(p + np.eye(len(p))[i] * h) - residuals(p - np.eye(len(p))[i] * h)) / (2 * h)
                        for i, h in enumerate(steps)], axis=1)
    analytic = _jacobian(p, views, n_lens, fixed)
    assert analytic.shape == numeric.shape
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-5 * np.abs(numeric).max())


def test_one_view_gives_the_camera_and_the_lens_under_the_pattern():
    views, K, poses = _views(1)
    cal = calibrate_lens(views[:1], SIZE)
    assert cal.rms_px[0] < 0.2  # 0.1 px noise: the model explains the points
    C_true = -poses[0][0].T @ poses[0][1]
    assert np.linalg.norm(-cal.R[0].T @ cal.t[0] - C_true) < 0.01 * np.linalg.norm(C_true)
    # where the pattern was, the lens is right
    X, x = views[0]
    R, t = poses[0]
    truth = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, LENS)[0].reshape(-1, 2)
    assert np.percentile(np.linalg.norm(project_distorted(cal.K, cal.R[0], cal.t[0], cal.distortion, X) - truth, axis=1),
                         95) < 0.3


def test_more_views_pin_the_lens_over_the_whole_frame():
    views, K, poses = _views(5)
    one = calibrate_lens(views[:1], SIZE)
    many = calibrate_lens(views, SIZE)
    R, t = poses[0]
    e1, e5 = _frame_error(one, K, LENS, R, t), _frame_error(many, K, LENS, R, t)
    assert np.percentile(e5, 95) < 0.5 and np.percentile(e5, 95) < np.percentile(e1, 95)
    assert abs(many.distortion[0] - LENS[0]) < 0.02  # k1; k2 trades against it, the frame error is what counts


def test_known_intrinsics_leave_only_the_pose():
    views, K, poses = _views(1, noise=0.05)
    cal = calibrate_lens(views[:1], SIZE, intrinsics=(K, LENS))
    np.testing.assert_array_equal(cal.K, K)
    np.testing.assert_array_equal(cal.distortion, LENS)
    assert np.linalg.norm((-cal.R[0].T @ cal.t[0]) - (-poses[0][0].T @ poses[0][1])) < 2.0  # mm at 1.5 m


def test_a_view_that_fits_badly_is_reported_and_refused_above_max_rms():
    """The RMS is a judgement: a warning naming the view, fatal only with a limit (--max-rms)."""
    views, K, _ = _views(2)
    X, x = views[1]
    bad = [views[0], (X, x + np.random.default_rng(3).normal(0, 10.0, x.shape))]
    with pytest.raises(StereoseedError, match=r"^b\.png: the pattern points reproject with \d+\.\d px RMS.*--max-rms 5"):
        calibrate_lens(bad, what=["a.png", "b.png"], intrinsics=(K, LENS), max_rms_px=5.0)
    cal = calibrate_lens(bad, what=["a.png", "b.png"], intrinsics=(K, LENS))
    assert cal.rms_px[0] < 0.3 and 9 < cal.rms_px[1] < 15
    assert len(cal.warnings) == 1 and cal.warnings[0].startswith("b.png: the pattern points reproject")


@pytest.mark.parametrize("seed, reason", [(2, r"fx and fy differ by 37 %.*principal point \(78, 17\) outside the "
                                                r"middle 50 % of the 640x480 frame.*tangential distortion"),
                                          (5, r"folds the image back")])
def test_a_camera_the_points_do_not_determine_is_refused_with_the_reason(seed, reason):
    """One view of a small pattern (a 60 mm box corner filling a tenth of the frame) with 1 px
    noise: 9 intrinsics and lens terms from 40 points; what comes out is no camera (seed 2: f =
    (633, 865) px, the principal point in a corner; seed 5: f = 399 px with k2 = -1305, a lens
    that folds the image), and is refused saying so."""
    rng = np.random.default_rng(seed)
    X = box_points(rng, 40, half=30.0, height=60.0)
    K, R, t, _ = look_at_camera((900.0, 500.0, 400.0), target=(0, 0, 30), f=800.0, pp=(320, 240))
    x = project_distorted(K, R, t, np.zeros(5), X) + rng.normal(0, 1.0, (len(X), 2))
    with pytest.raises(StereoseedError, match=rf"^v\.png: refused, no physical camera: .*{reason}"):
        calibrate_lens([(X, x)], SIZE, what=["v.png"])


def test_calib_json_and_opencv_files_give_the_lens(tmp_path):
    views, K, _ = _views(1)
    cal = calibrate_lens(views, SIZE)
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps({"cameras": [cal.to_dict(), {"P": cal.P.tolist()}]}))
    lenses = read_lenses(calib)
    np.testing.assert_allclose(lenses[0].distortion, cal.distortion)
    assert lenses[0].image_size == SIZE and lenses[1] is None
    fs = cv2.FileStorage(str(tmp_path / "cam.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", LENS.reshape(1, 5))
    fs.release()
    K2, d2, _ = read_opencv_camera(tmp_path / "cam.yaml")
    np.testing.assert_allclose(K2, K)
    np.testing.assert_allclose(d2, LENS)
    (tmp_path / "bad.yaml").write_text("%YAML:1.0\nfoo: 1\n")
    with pytest.raises(StereoseedError, match="camera_matrix"):
        read_opencv_camera(tmp_path / "bad.yaml")


_READ_DEEP = """
import sys
from stereoseed.calibration.lens_calibration import read_opencv_camera
from stereoseed.errors import StereoseedError
try:
    read_opencv_camera(sys.argv[1])
except StereoseedError as e:
    print(e)
"""


@pytest.mark.parametrize("name, text", [
    ("flow.yaml", "%YAML:1.0\n---\ncamera_matrix: " + "[" * 100000 + "]" * 100000 + "\n"),
    ("dashes.yaml", "%YAML:1.0\n---\ncamera_matrix:\n  " + "- " * 100000 + "1\n"),
    ("deep.xml", '<?xml version="1.0"?>\n<opencv_storage>' + "<a>" * 100000 + "</a>" * 100000 + "</opencv_storage>\n"),
    ("deep.json", '{"camera_matrix": ' + "[" * 100000 + "]" * 100000 + "}"),
])
def test_a_deeply_nested_intrinsics_file_is_refused_not_a_crash(tmp_path, name, text):
    """Issue 48 row 6: OpenCV's FileStorage recursed into a deeply nested file until the process
    died of SIGSEGV (in a child process here, so that the old code's crash is a failure)."""
    import subprocess
    import sys

    path = tmp_path / name
    path.write_text(text)
    done = subprocess.run([sys.executable, "-c", _READ_DEEP, str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-300:]
    assert done.stdout.startswith(f"{path}: nested ") and "more than any calibration file (64 at most)" in done.stdout


@pytest.mark.parametrize("size", [float("inf"), float("nan"), 1e30, 640.5, -640])
def test_an_image_size_that_is_no_whole_number_of_pixels_is_refused_naming_it(tmp_path, size):
    """Issue 48 row 11: calib.json's image_size and a YAML's image_width of .inf were an
    OverflowError traceback; NaN was blamed on the distortion, 1e30 accepted."""
    views, K, _ = _views(1)
    cal = calibrate_lens(views, SIZE)
    entry = cal.to_dict() | {"image_size": [size, 480]}
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps({"cameras": [entry, {"P": cal.P.tolist()}]}))
    with pytest.raises(StereoseedError, match=r"calib.json: camera 0: image_size: expected the image's width and "
                                              r"height in pixels, two whole numbers from 1 to 65535"):
        read_lenses(calib)
    yaml = tmp_path / "cam.yaml"
    fs = cv2.FileStorage(str(yaml), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", LENS.reshape(1, 5))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    assert read_opencv_camera(yaml)[2] == (640, 480)
    text = yaml.read_text().replace("image_width: 640", f"image_width: {'.inf' if size == float('inf') else size}")
    yaml.write_text(text.replace("image_width: nan", "image_width: .nan"))
    with pytest.raises(StereoseedError, match="cam.yaml: image_width, image_height: expected the image's width"):
        read_opencv_camera(yaml)
    # row 13: a zero K undistorted every image into black, said as "no interest points"
    calib.write_text(json.dumps({"cameras": [cal.to_dict() | {"K": np.zeros((3, 3)).tolist()}, {"P": cal.P.tolist()}]}))
    with pytest.raises(StereoseedError, match=r"calib.json: camera 0: K \[\[0.0, 0.0, 0.0\].* is no camera"):
        read_lenses(calib)
    # row 13: [640, 480, 3] (a NumPy shape's tail) was taken as 640x480 and blamed on the images
    calib.write_text(json.dumps({"cameras": [cal.to_dict() | {"image_size": [640, 480, 3]}, {"P": cal.P.tolist()}]}))
    with pytest.raises(StereoseedError, match=r"image_size: expected .* got \[640, 480, 3\]"):
        read_lenses(calib)
