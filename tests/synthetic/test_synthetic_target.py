"""Rendering a planar-faced calibration target (stereoseed.synthetic.target) against its contract."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stereoseed.errors import StereoseedError
from stereoseed.geometry.lens import project_distorted
from stereoseed.synthetic.target import (
    default_background,
    face_points,
    load_target,
    render_target,
)

LENS = (-0.12, 0.03, 0.001, -0.0005)
K = np.array([[800.0, 0.0, 321.0], [0.0, 800.0, 238.5], [0.0, 0.0, 1.0]])
SIZE = (640, 480)
PITCH = 0.1  # mm per face pixel: 2000 x 1500 px faces, far finer than the screen (mip tested)
FACE_W, FACE_H = 2000, 1500
MARGIN, SQUARE = 150, 200  # face pixels: 8 x 6 squares of 20 mm


def _checkerboard() -> np.ndarray:
    img = np.full((FACE_H, FACE_W), 255, np.uint8)
    for row in range(6):
        for col in range(8):
            if (row + col) % 2 == 0:
                v0, u0 = MARGIN + row * SQUARE, MARGIN + col * SQUARE
                img[v0:v0 + SQUARE, u0:u0 + SQUARE] = 0
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def _inner_corners_uv() -> np.ndarray:
    """The 7 x 5 inner corners of a face's checkerboard, face-image coordinates (N, 2)."""
    k, m = np.meshgrid(np.arange(1, 8), np.arange(1, 6))
    return np.column_stack([(MARGIN + SQUARE * k - 0.5).ravel(), (MARGIN + SQUARE * m - 0.5).ravel()])


@pytest.fixture(scope="module")
def target_dir(tmp_path_factory):
    """Two perpendicular 200 x 150 mm faces, a convex edge along the z axis (a box's corner):
    face 0 on y = 0 (x in [0, 200]) printed towards -y, face 1 on x = 0 (y in [0, 200]) printed
    towards -x; image rows go down (-z)."""
    folder = tmp_path_factory.mktemp("target")
    board = _checkerboard()
    cv2.imwrite(str(folder / "face_0.png"), board)
    cv2.imwrite(str(folder / "face_1.png"), board)
    doc = {"unit": "mm", "faces": [
        {"image": "face_0.png", "origin": [0.5 * PITCH, 0.0, 150.0 - 0.5 * PITCH],
         "u_axis": [PITCH, 0, 0], "v_axis": [0, 0, -PITCH]},
        {"image": "face_1.png", "origin": [0.0, 200.0 - 0.5 * PITCH, 150.0 - 0.5 * PITCH],
         "u_axis": [0, -PITCH, 0], "v_axis": [0, 0, -PITCH]},
    ]}
    (folder / "target.json").write_text(json.dumps(doc))
    return folder


def _look_at(center, target):
    """R, t of a camera at center looking at target, image y ~ world -z."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ center


def _view(azimuth_deg=225.0, distance=420.0, height=260.0, look=(40.0, 40.0, 70.0)):
    a = np.radians(azimuth_deg)
    center = np.array(look) + np.array([distance * np.cos(a), distance * np.sin(a), 0.0])
    center[2] = height
    return _look_at(center, look)


def test_face_points_follow_the_contract(target_dir):
    target = load_target(target_dir / "target.json")
    assert target.unit == "mm" and len(target.faces) == 2
    f0, f1 = target.faces
    assert f0.image.shape == (FACE_H, FACE_W, 3)
    np.testing.assert_allclose(face_points(f0, [[-0.5, -0.5]]), [[0.0, 0.0, 150.0]], atol=1e-12)
    np.testing.assert_allclose(face_points(f1, [[FACE_W - 0.5, FACE_H - 0.5]]), [[0, 0, 0]],
                               atol=1e-12)
    np.testing.assert_allclose(f0.printed_normal, [0, -1, 0])
    np.testing.assert_allclose(f1.printed_normal, [-1, 0, 0])


@pytest.mark.parametrize("distortion", [(), LENS], ids=["pinhole", "lens"])
@pytest.mark.parametrize("azimuth, distance", [(225.0, 420.0), (200.0, 420.0), (225.0, 300.0)])
def test_checkerboard_corners_land_on_their_projections(target_dir, distortion, azimuth,
                                                         distance):
    """Corners from the contract, projected (through the lens), are where cv2.cornerSubPix finds
    the rendered corners: <= 0.12 px measured (the faces are 2000 x 1500 px, mip-mapped)."""
    target = load_target(target_dir / "target.json")
    R, t = _view(azimuth, distance)
    image = render_target(target, K, R, t, SIZE, distortion=distortion, background=128)
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    errors, moved = [], []
    for face in target.faces:
        X = face_points(face, _inner_corners_uv())
        if np.dot(face.printed_normal, -R.T @ t - X[0]) <= 0:
            continue
        uv = project_distorted(K, R, t, distortion, X)
        # cornerSubPix's 11 x 11 window must hold one corner only: skip foreshortened squares.
        gap = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.diag(np.full(len(uv), np.inf))
        inside = np.all((uv > 12) & (uv < np.array(SIZE) - 13), axis=1) & (gap.min(axis=1) > 20)
        uv = uv[inside]
        if not len(uv):
            continue
        start = uv.astype(np.float32).reshape(-1, 1, 2).copy()
        found = cv2.cornerSubPix(gray, start, (5, 5), (-1, -1),
                                 (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
        errors.append(np.linalg.norm(found.reshape(-1, 2) - uv, axis=1))
        moved.append(np.linalg.norm(uv - project_distorted(K, R, t, (), X[inside]), axis=1))
    errors = np.concatenate(errors)
    assert len(errors) >= 30
    assert errors.max() < 0.2, errors.max()
    if distortion:  # the lens moved them farther than the tolerance: the check has teeth
        assert np.concatenate(moved).max() > 0.8


def test_faces_seen_from_behind_are_not_drawn(target_dir):
    target = load_target(target_dir / "target.json")
    # From inside the "box" (x, y > 0) both printed sides face away: background only.
    R, t = _look_at(np.array([300.0, 300.0, 200.0]), [0.0, 0.0, 75.0])
    image = render_target(target, K, R, t, SIZE, background=(90, 100, 110))
    assert np.all(image == np.array([90, 100, 110], np.uint8))
    # From the -y side only face 0 is drawn: face 1 (printed towards -x) is seen edge-on to
    # behind; the part of the image left of the edge x = 0 shows background.
    R, t = _look_at(np.array([100.0, -400.0, 75.0]), [100.0, 0.0, 75.0])
    image = render_target(target, K, R, t, SIZE, background=128)
    edge = project_distorted(K, R, t, (), [[0.0, 0.0, 75.0]])[0]
    assert 20 < edge[0] < 300
    assert np.all(image[:, : int(edge[0]) - 2] == 128)
    right = image[100:380, int(edge[0]) + 3:]
    assert (right == 0).mean() > 0.2 and (right == 255).mean() > 0.2


def test_nearest_face_wins(tmp_path):
    # A white 10 x 10 face in front of a black 40 x 40 one, both printed towards +z; the camera
    # looks down from +z: white in the middle, black around, never the other way.
    cv2.imwrite(str(tmp_path / "white.png"), np.full((10, 10, 3), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((40, 40, 3), np.uint8))
    faces = [
        # printed towards +z: -(u x v) = +z with u = +x, v = -y (rows go down the image)
        {"image": "black.png", "origin": [-19.5, 19.5, -50.0], "u_axis": [1, 0, 0],
         "v_axis": [0, -1, 0]},
        {"image": "white.png", "origin": [-4.5, 4.5, 0.0], "u_axis": [1, 0, 0],
         "v_axis": [0, -1, 0]},
    ]
    for order in (faces, faces[::-1]):
        (tmp_path / "target.json").write_text(json.dumps({"unit": "mm", "faces": order}))
        R = np.diag([1.0, -1.0, -1.0])  # looking down -z, image x = +x
        t = -R @ np.array([0.0, 0.0, 100.0])
        image = render_target(tmp_path / "target.json", K, R, t, SIZE, supersample=1,
                              background=128)
        centre = project_distorted(K, R, t, (), [[0.0, 0.0, 0.0]])[0].astype(int)
        assert np.all(image[centre[1], centre[0]] == 255)
        ring = project_distorted(K, R, t, (), [[12.0, 0.0, -50.0]])[0].astype(int)
        assert np.all(image[ring[1], ring[0]] == 0)
        far = project_distorted(K, R, t, (), [[30.0, 0.0, -50.0]])[0].astype(int)
        assert np.all(image[far[1], far[0]] == 128)


def test_background_noise_and_errors(target_dir, tmp_path):
    bg = default_background(SIZE, seed=3)
    assert bg.shape == (480, 640, 3) and abs(bg.mean() - 128) < 2 and 2 < bg.std() < 6
    R, t = _look_at(np.array([300.0, 300.0, 200.0]), [0.0, 0.0, 75.0])  # background only
    plain = render_target(target_dir / "target.json", K, R, t, SIZE, seed=3)
    np.testing.assert_array_equal(plain, np.clip(np.rint(bg), 0, 255).astype(np.uint8))
    noisy = render_target(target_dir / "target.json", K, R, t, SIZE, seed=3, noise_sigma=2.0)
    d = noisy.astype(float) - plain
    assert d.std() == pytest.approx(2.0, rel=0.1)
    np.testing.assert_array_equal(
        noisy, render_target(target_dir / "target.json", K, R, t, SIZE, seed=3, noise_sigma=2.0))
    with pytest.raises(StereoseedError, match="not found"):
        load_target(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text(json.dumps({"unit": "mm", "faces": [
        {"image": "face.png", "origin": [0, 0, 0], "u_axis": [1, 0, 0], "v_axis": [2, 0, 0]}]}))
    with pytest.raises(StereoseedError, match="parallel"):
        load_target(tmp_path / "bad.json")


def test_fine_print_is_area_averaged_not_aliased(tmp_path):
    # 1-texel black / white stripes (0.1 mm) seen at ~0.2 px per texel: without the
    # pre-downscale, supersampled point samples would alias into bands; with it the face is an
    # even grey of the stripes' mean.
    stripes = np.zeros((FACE_H, FACE_W, 3), np.uint8)
    stripes[:, ::2] = 255
    stripes[::2] = 255 - stripes[::2]  # a checker of single texels
    cv2.imwrite(str(tmp_path / "fine.png"), stripes)
    (tmp_path / "target.json").write_text(json.dumps({"unit": "mm", "faces": [
        {"image": "fine.png", "origin": [0.5 * PITCH, 0.0, 150.0 - 0.5 * PITCH],
         "u_axis": [PITCH, 0, 0], "v_axis": [0, 0, -PITCH]}]}))
    R, t = _look_at(np.array([100.0, -500.0, 120.0]), [100.0, 0.0, 75.0])
    image = render_target(tmp_path / "target.json", K, R, t, SIZE, background=0)
    corners = project_distorted(K, R, t, (), [[20, 0, 130], [180, 0, 20]])
    (u0, v0), (u1, v1) = np.rint(corners).astype(int)
    patch = image[v0:v1, u0:u1].astype(float)
    assert patch.size > 100_000
    assert abs(patch.mean() - 127.5) < 2 and patch.std() < 2, (patch.mean(), patch.std())


def test_a_target_described_by_numbers_is_drawn_where_it_says(tmp_path):
    """from_boards: a board given by its numbers only (no face image), drawn by OpenCV and placed
    by the contract, then moved by a known pose: every corner is where the moved contract projects
    it (the saddle-fitted corners within 0.02 px; OpenCV's cornerSubPix, pulled by the marker
    edges, within 0.6 px, its ids all there)."""
    from stereoseed.calibration.detection import charuco_shift, detect_target
    from stereoseed.calibration.target import load_target as load_description
    from stereoseed.synthetic.target import from_boards

    spec = {"unit": "mm", "faces": [{"origin": [0.0, 0.0, 0.0], "u_axis": [1.0, 0.0, 0.0], "v_axis": [0.0, 1.0, 0.0],
                                     "board": {"dictionary": "DICT_4X4_50", "squares": [7, 5], "square_px": 25.0,
                                               "marker_px": 18.0, "first_id": 0, "origin_uv": [0.0, 0.0]}}]}
    (tmp_path / "board.json").write_text(json.dumps(spec))
    description = load_description(tmp_path / "board.json")
    move = (cv2.Rodrigues(np.array([0.0, 0.0, np.radians(5.0)]))[0], np.array([3.0, -2.0, 1.0]))
    target = from_boards(description, texels_per_square=40, poses=[move])
    R, t = np.eye(3), np.array([-87.5, -62.5, 300.0])  # the board's middle on the axis, 300 mm away
    image = render_target(target, K, R, t, SIZE, supersample=4)
    board = description.faces[0].board
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    X = description.faces[0].to_3d(board.corner_uv(ids.ravel())) @ move[0].T + move[1]
    expected = project_distorted(K, R, t, np.zeros(5), X)
    corners = corners.reshape(-1, 2) - charuco_shift()  # OpenCV's half-pixel bias before 5.x
    assert len(ids) == board.n_corners and np.abs(corners - expected).max() < 0.6
    found = detect_target(image, description)
    X = found.points3d @ move[0].T + move[1]
    assert found.refined.all() and np.abs(found.pixels - project_distorted(K, R, t, np.zeros(5), X)).max() < 0.02
    assert target.faces[0].image.shape[:2] == (5 * 40 + 80, 7 * 40 + 80)  # one square of white around the board
