"""The synthetic box scene: its geometry, its cameras, its rendering and its ground truth."""
from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest

from stereoseed.geometry.projection import camera_center, compose_projection, project
from stereoseed.features.edge_corners import corners_on_edges
from stereoseed.features.image import to_gray
from stereoseed.geometry.lens import distort_pixels, undistort_image, undistort_pixels
from stereoseed.synthetic.render import add_noise
from stereoseed.synthetic.scene import (
    BOX_HALF,
    BOX_HEIGHT,
    FACE_NORMALS,
    FACE_ORIGIN,
    FACE_U,
    FACE_V,
    GROUND_RADIUS,
    SQUARE_SIZE,
    SceneConfig,
    box_corners,
    render_scene,
    write_scene,
)


def _dark_square_centroid(grey, poly):
    """(expected, measured) centroid (2,) of a dark square whose outline projects to ``poly``
    (K, 2): the polygon's centroid, and the darkness-weighted centroid of the image inside the
    polygon grown by 40 % around it (which stays within the gaps); None for a tiny square."""
    x, y = poly[:, 0], poly[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = cross.sum() / 2
    if abs(area) < 150:
        return None
    expected = np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * area)
    grown = expected + 1.4 * (poly - expected)
    mask = np.zeros(grey.shape, np.uint8)
    cv2.fillPoly(mask, [np.rint(grown).astype(np.int32)], 1)
    vv, uu = np.nonzero(mask)
    g = grey[vv, uu]
    light, dark = np.percentile(g, 95), g.min()
    w = np.clip((light - g) / (light - dark), 0.0, 1.0)
    return expected, np.array([np.sum(w * uu), np.sum(w * vv)]) / w.sum()


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)


def _local(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Face-local (s, r) coordinates of points (N, 3) on box faces labels (N,) -> (N, 2)."""
    d = points - FACE_ORIGIN[labels]
    return np.stack([np.einsum("nk,nk->n", d, FACE_U[labels]),
                     np.einsum("nk,nk->n", d, FACE_V[labels])], axis=1)


# --- the target's geometry ---------------------------------------------------------------------


def test_228_corners_57_squares_on_the_box():
    corners, labels = box_corners()
    assert corners.shape == (228, 3) and corners.dtype == np.float64
    assert len(np.unique(np.round(corners, 9), axis=0)) == 228
    assert np.bincount(labels, minlength=6).tolist() == [0, 48, 48, 48, 48, 36]
    # Each corner lies on its face plane, at least one gap (4 cm) inside the face's edges.
    offset = np.einsum("nk,nk->n", corners - FACE_ORIGIN[labels], FACE_NORMALS[labels])
    np.testing.assert_allclose(offset, 0.0, atol=1e-12)
    sr = _local(corners, labels)
    extent = np.where(labels[:, None] == 5, [0.34, 0.34], [0.34, 0.44])
    assert np.all(sr >= 0.04 - 1e-12) and np.all(sr <= extent - 0.04 + 1e-12)
    assert np.all(np.abs(corners[:, :2]) <= BOX_HALF + 1e-12)
    assert np.all((corners[:, 2] >= 0) & (corners[:, 2] <= BOX_HEIGHT + 1e-12))


def test_squares_are_6cm_counter_clockwise_from_outside_with_4cm_gaps():
    corners, labels = box_corners()
    squares = corners.reshape(57, 4, 3)
    edges = np.roll(squares, -1, axis=1) - squares
    np.testing.assert_allclose(np.linalg.norm(edges, axis=2), SQUARE_SIZE, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nk->n", edges[:, 0], edges[:, 1]), 0.0, atol=1e-12)
    normal = np.cross(edges[:, 0], edges[:, 1]) / SQUARE_SIZE**2
    np.testing.assert_allclose(normal, FACE_NORMALS[labels[::4]], atol=1e-12)
    # Neighbouring squares on a face are one gap apart: closest corners of different squares.
    for f in range(1, 6):
        sq = squares[labels[::4] == f]
        d = np.linalg.norm(sq[:, None, :, None] - sq[None, :, None, :], axis=-1).min(axis=(2, 3))
        np.fill_diagonal(d, np.inf)
        np.testing.assert_allclose(d.min(), 0.04, atol=1e-12)


# --- cameras -----------------------------------------------------------------------------------


def test_cameras_are_consistent_upright_and_look_at_the_box(box_scene):
    cfg = box_scene.config
    assert box_scene.n_images == len(box_scene.P) == cfg.n_images == 14
    assert box_scene.names[0] == "img_000.png" and box_scene.names[13] == "img_013.png"
    s = box_scene
    for P, K, R, t, image in zip(s.P, s.K, s.R, s.t, s.images):
        assert image.shape == (480, 640, 3) and image.dtype == np.uint8
        np.testing.assert_allclose(P, compose_projection(K, R, t), atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert R[1] @ np.array([0.0, 0.0, -1.0]) > 0.85  # image y down ~ world -z
        centre = camera_center(P)
        assert 1.2 < np.linalg.norm(centre - [0, 0, 0.2]) < 1.6
        uv = project(P, np.array([[0.0, 0.0, 0.22]]))[0]  # box centre near the image centre
        assert np.all(np.abs(uv - [319.5, 239.5]) < 60)
    # Azimuths step by ~20 degrees around the z axis.
    az = np.degrees(np.unwrap(np.arctan2(box_scene.centers[:, 1], box_scene.centers[:, 0])))
    np.testing.assert_allclose(np.diff(az), cfg.step_deg, atol=3.0)


def test_moving_camera_focal_varies_within_10_percent(box_scene):
    K1 = box_scene.K[1]
    assert K1[0, 0] == box_scene.config.focal_px
    focals = np.array([K[0, 0] for K in box_scene.K[2:]])
    assert np.all(np.abs(focals / K1[0, 0] - 1.0) <= 0.10)
    assert np.ptp(focals) > 0.02 * K1[0, 0]
    for K in box_scene.K[2:]:
        assert K[0, 1] == 0.0 and K[0, 0] == K[1, 1]
        np.testing.assert_array_equal(K[:2, 2], K1[:2, 2])
    # Camera 0 is another physical camera.
    assert box_scene.K[0][0, 0] != K1[0, 0] and np.any(box_scene.K[0][:2, 2] != K1[:2, 2])


# --- rendering against the ground truth -------------------------------------------------------


def _visible_square_corner_pairs(scene, i):
    """For the visible corners of image i: pixel (rounded) just inside and just outside its square.

    Keeps only corners where both pixels are safely (>= 1.6 px) away from the square's edge lines
    in the image, so anti-aliasing cannot blur them.
    """
    corners, labels = scene.corners, scene.corner_labels
    centres = corners.reshape(57, 4, 3).mean(axis=1).repeat(4, axis=0)
    vis = scene.corner_visibility(i)
    squares = corners.reshape(57, 4, 3).repeat(4, axis=0)
    k = np.arange(228) % 4
    prev_c, next_c = squares[np.arange(228), (k - 1) % 4], squares[np.arange(228), (k + 1) % 4]
    P = scene.P[i]
    c = project(P, corners)
    pairs = []
    for sign, frac in ((1.0, 0.4), (-1.0, 0.4)):  # inside / outside along the diagonal
        x = project(P, corners + sign * frac * (centres - corners))
        dist = np.full(228, np.inf)
        for other in (prev_c, next_c):  # distance of x to both image edge lines at the corner
            e = project(P, other) - c
            w = x - c
            across = np.abs(e[:, 0] * w[:, 1] - e[:, 1] * w[:, 0]) / np.linalg.norm(e, axis=1)
            dist = np.minimum(dist, across)
        pairs.append((np.rint(x).astype(int), dist))
    (inside, d_in), (outside, d_out) = pairs
    keep = vis & (d_in > 1.6) & (d_out > 1.6)
    return inside[keep], outside[keep], labels[keep]


@pytest.mark.parametrize("scene_name", ["box_scene", "plain_box_scene"])
@pytest.mark.parametrize("i", [0, 1, 4, 9])
def test_projected_corners_match_the_dark_squares(request, scene_name, i):
    scene = request.getfixturevalue(scene_name)
    grey = _grey(scene.images[i])
    inside, outside, _ = _visible_square_corner_pairs(scene, i)
    assert len(inside) >= 60
    g_in = grey[inside[:, 1], inside[:, 0]]
    g_out = grey[outside[:, 1], outside[:, 0]]
    assert np.all(g_in < 50)
    assert np.all(g_out > 70)
    assert np.all(g_out - g_in > 35)


@pytest.mark.parametrize("i", [1, 6])
def test_dark_square_centroids_match_projection_subpixel(plain_box_scene, i):
    """Anti-aliased coverage of each square in the plain render has the projected centroid.

    Checks the pixel-centre convention and the supersampling pattern to ~0.1 px.
    """
    scene = plain_box_scene
    grey = _grey(scene.images[i])
    P = scene.P[i]
    squares = scene.corners.reshape(57, 4, 3)
    vis = scene.corner_visibility(i).reshape(57, 4).all(axis=1)
    errors = []
    for sq in squares[vis]:
        found = _dark_square_centroid(grey, project(P, sq))
        if found is not None:
            errors.append(np.linalg.norm(found[1] - found[0]))
    assert len(errors) >= 15
    assert np.max(errors) < 0.1


def test_plain_scene_is_untextured(plain_box_scene, box_scene):
    for scene, textured in ((plain_box_scene, False), (box_scene, True)):
        grey = _grey(scene.images[2])
        _, labels = scene.surface_points(2)
        ground = cv2.erode((labels == 0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        if textured:
            assert grey[ground].std() > 10
        else:
            assert grey[ground].std() < 1.0


def test_box_faces_have_texture_for_matching(box_scene):
    grey = _grey(box_scene.images[0]) / 255.0
    _, labels = box_scene.surface_points(0)
    s = np.zeros_like(grey)  # Lhuillier-Quan texture measure, max |difference| to 4 neighbours
    s[1:-1, 1:-1] = np.max(np.abs(np.stack([grey[1:-1, 2:], grey[1:-1, :-2], grey[2:, 1:-1],
                                            grey[:-2, 1:-1]]) - grey[1:-1, 1:-1]), axis=0)
    box = labels > 0
    assert np.mean(s[box] > 0.01) > 0.8
    # Colours: the box is warm (R > B in BGR order), the ground disk cool (B > R).
    image = box_scene.images[0].astype(float)
    assert image[box, 2].mean() > image[box, 0].mean() + 20
    radius = np.linalg.norm(box_scene.surface_points(0)[0][..., :2], axis=-1)
    near_ground = (labels == 0) & (radius < GROUND_RADIUS)
    assert image[near_ground, 0].mean() > image[near_ground, 2].mean() + 20


# --- exact ground truth ------------------------------------------------------------------------


@pytest.mark.parametrize("i", [0, 7])
def test_surface_points_reproject_to_pixel_centres(box_scene, i):
    points, labels = box_scene.surface_points(i)
    H, W = labels.shape
    assert points.shape == (H, W, 3) and labels.dtype == np.int8
    hit = labels >= 0
    assert np.all(np.isnan(points[~hit])) and not np.any(np.isnan(points[hit]))
    v, u = np.nonzero(hit)
    uv = project(box_scene.P[i], points[hit])
    assert np.max(np.abs(uv - np.stack([u, v], axis=1))) < 1e-6
    # Every label lies on its surface.
    lab = labels[hit]
    X = points[hit]
    assert np.all(X[lab == 0, 2] == 0.0)
    assert np.all(np.any(np.abs(X[lab == 0, :2]) >= BOX_HALF, axis=1))
    on_box = lab > 0
    offset = np.einsum("nk,nk->n", X[on_box] - FACE_ORIGIN[lab[on_box]], FACE_NORMALS[lab[on_box]])
    assert np.all(offset == 0.0)
    assert set(np.unique(lab[on_box])) <= {1, 2, 3, 4, 5} and len(np.unique(lab[on_box])) >= 2
    # Only faces turned towards the camera are seen.
    C = camera_center(box_scene.P[i])
    assert np.all(np.einsum("nk,nk->n", FACE_NORMALS[lab[on_box]], C - X[on_box]) > 0)
    assert box_scene.surface_points(i)[0] is points  # cached


def test_is_visible_agrees_with_surface_points(box_scene):
    i = 3
    points, labels = box_scene.surface_points(i)
    hit = labels >= 0
    X = points[hit][::97]
    assert np.all(box_scene.is_visible(i, X))
    C = camera_center(box_scene.P[i])
    ray = (X - C) / np.linalg.norm(X - C, axis=1, keepdims=True)
    assert not np.any(box_scene.is_visible(i, X + 0.01 * ray))  # behind the seen surface
    assert np.all(box_scene.is_visible(i, X - 0.01 * ray))  # in the air before it
    # Margin: points near the border drop out.
    v, u = np.nonzero(hit)
    near_border = (u[::97] < 5) | (v[::97] < 5) | (u[::97] > 634) | (v[::97] > 474)
    assert near_border.any()
    assert not np.any(box_scene.is_visible(i, X, margin=6.0)[near_border])
    # Behind the camera.
    assert not box_scene.is_visible(i, (2 * C - X[:5])).any()


def test_sampled_surface_points_visibility_matches_rendered_labels(box_scene):
    rng = np.random.default_rng(1)
    X, lab = box_scene.sample_surface_points(20000, rng)
    assert X.shape == (20000, 3) and lab.shape == (20000,)
    assert set(np.unique(lab)) == {0, 1, 2, 3, 4, 5}
    g = lab == 0
    assert np.all(X[g, 2] == 0) and np.all(np.linalg.norm(X[g, :2], axis=1) <= GROUND_RADIUS)
    assert np.all(np.any(np.abs(X[g, :2]) >= BOX_HALF, axis=1))
    # Uniform by area: the ground disk holds ~ (pi - 0.1156) / (pi - 0.1156 + 0.714) of the samples.
    assert g.mean() == pytest.approx((np.pi - 0.1156) / (np.pi - 0.1156 + 0.714), abs=0.02)
    Xb, labb = box_scene.sample_surface_points(5000, rng, include_ground=False)
    assert np.all(labb > 0)
    sr = _local(Xb, labb)
    assert np.all(sr >= 0) and np.all(sr[:, 0] <= 0.34)
    assert np.all(sr[:, 1] <= np.where(labb == 5, 0.34, 0.44))

    for i in (0, 8):
        points, labels = box_scene.surface_points(i)
        vis = box_scene.is_visible(i, X)
        uv = np.rint(project(box_scene.P[i], X[vis])).astype(int)
        assert vis.sum() > 3000
        same = labels[uv[:, 1], uv[:, 0]] == lab[vis]
        assert same.mean() > 0.99  # disagreements only along silhouettes / face edges
        assert np.median(np.linalg.norm(points[uv[:, 1], uv[:, 0]] - X[vis], axis=1)) < 0.003
        # A point on a face turned away from the camera is never visible.
        C = camera_center(box_scene.P[i])
        away = (lab > 0) & (np.einsum("nk,nk->n", FACE_NORMALS[lab], C - X) < 0)
        assert away.any() and not vis[away].any()


def test_corner_visibility(box_scene):
    counts = []
    for i in range(box_scene.n_images):
        vis = box_scene.corner_visibility(i)
        assert vis.shape == (228,) and vis.dtype == bool
        uv = project(box_scene.P[i], box_scene.corners[vis])
        assert np.all((uv >= 9.5) & (uv <= [640 - 10.5, 480 - 10.5]))
        C = camera_center(box_scene.P[i])
        normals = FACE_NORMALS[box_scene.corner_labels[vis]]
        assert np.all(np.einsum("nk,nk->n", normals, C - box_scene.corners[vis]) > 0)
        counts.append(vis.sum())
    # A ring view sees the top and one or two side faces completely.
    assert set(counts) <= {84, 132}


def test_calibration_points(box_scene):
    pattern, p1, p2 = box_scene.calibration_points()
    assert pattern.shape[0] >= 50 and p1.shape == p2.shape == (pattern.shape[0], 2)
    centred = pattern - pattern.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    assert sv[-1] / sv[0] > 0.1  # well spread in 3D, far from coplanar
    e1 = p1 - project(box_scene.P[0], pattern)
    e2 = p2 - project(box_scene.P[1], pattern)
    sigma = np.concatenate([e1, e2]).std()
    assert sigma == pytest.approx(box_scene.config.calib_noise_px, rel=0.2)
    again = box_scene.calibration_points()
    np.testing.assert_array_equal(again[1], p1)


# --- determinism, noise, files -----------------------------------------------------------------


def test_deterministic_and_independent_of_n_images(box_scene, box_scene_noisy):
    short = render_scene(SceneConfig(n_images=2))
    for i in range(2):
        np.testing.assert_array_equal(short.images[i], box_scene.images[i])
        np.testing.assert_array_equal(short.P[i], box_scene.P[i])
    other = render_scene(SceneConfig(n_images=2, seed=1))
    assert not np.array_equal(other.images[1], short.images[1])
    # so a scene's prefix is the shorter scene (the tests take theirs from the session's rings),
    # image noise included, and a copy
    for scene, rendered in ((box_scene, short), (box_scene_noisy, render_scene(SceneConfig(n_images=2, noise_sigma=2.0)))):
        prefix = scene.prefix(2)
        assert prefix.config == rendered.config and prefix.names == rendered.names
        for got, want in ((prefix.images, rendered.images), (prefix.P, rendered.P), (prefix.K, rendered.K),
                          (prefix.R, rendered.R), (prefix.t, rendered.t)):
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
        prefix.images[0][:] = 0
        assert scene.images[0].any()


def test_add_noise_has_requested_sigma():
    rng = np.random.default_rng(0)
    flat = np.full((400, 500, 3), 128, np.uint8)
    noisy = add_noise(flat, 2.0, rng)
    assert noisy.dtype == np.uint8 and noisy.shape == flat.shape
    d = noisy.astype(float) - 128
    assert d.std() == pytest.approx(2.0, rel=0.03) and abs(d.mean()) < 0.05
    np.testing.assert_array_equal(noisy[..., 0], noisy[..., 2])  # one sample per pixel
    assert np.array_equal(add_noise(flat, 0.0, rng), flat)
    clipped = add_noise(np.full((10, 10), 254, np.uint8), 50.0, rng)
    assert clipped.max() == 255


def test_rendered_noise_sigma(box_scene):
    noisy = render_scene(SceneConfig(n_images=2, noise_sigma=2.0))
    for i in range(2):
        np.testing.assert_array_equal(noisy.P[i], box_scene.P[i])
        d = _grey(noisy.images[i]) - _grey(box_scene.images[i])
        assert d.std() == pytest.approx(2.0, rel=0.1)


def test_write_scene(box_scene, tmp_path):
    out = tmp_path / "new" / "scene"
    written = write_scene(box_scene, out)
    assert [p.name for p in written["images"]] == box_scene.names
    back = cv2.imread(str(written["images"][5]), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(back, box_scene.images[5])
    cams = json.loads(written["cameras"].read_text())["images"]
    assert [c["name"] for c in cams] == box_scene.names
    np.testing.assert_allclose(cams[3]["P"], box_scene.P[3])
    np.testing.assert_allclose(cams[3]["center"], camera_center(box_scene.P[3]))
    np.testing.assert_allclose(np.loadtxt(written["corners"]), box_scene.corners, atol=1e-10)
    pattern, p1, p2 = box_scene.calibration_points()
    np.testing.assert_allclose(np.loadtxt(written["pattern"]), pattern, atol=1e-10)
    np.testing.assert_allclose(np.loadtxt(written["points1"]), p1, atol=1e-6)
    np.testing.assert_allclose(np.loadtxt(written["points2"]), p2, atol=1e-6)
    listed = written["images_txt"].read_text().split()
    assert listed == box_scene.names and all((out / name).is_file() for name in listed)


# --- a lens ------------------------------------------------------------------------------------

# sha256 of the bytes of render_scene(SceneConfig(n_images=2)).images, computed before lenses
# existed: without a lens the renderer must not change by a single bit.
_NO_LENS_SHA256 = "2fd51485aaf0961e96363df18809a5fb82d0bd9218143e74018cdfa8ee1cce3d"
LENS = (-0.12, 0.03, 0.001, -0.0005)


def _sha256(images) -> str:
    h = hashlib.sha256()
    for image in images:
        h.update(np.ascontiguousarray(image).tobytes())
    return h.hexdigest()


def test_no_lens_render_is_bit_identical():
    scene = render_scene(SceneConfig(n_images=2))
    assert scene.distortion == () and not scene.has_lens
    assert _sha256(scene.images) == _NO_LENS_SHA256
    # All-zero coefficients are no lens either: the pinhole kernel, the same bytes.
    zero = render_scene(SceneConfig(n_images=2, distortion=(0.0, 0.0, 0.0, 0.0)))
    assert _sha256(zero.images) == _NO_LENS_SHA256


def test_distortion_is_validated():
    with pytest.raises(ValueError, match="4 or 5"):
        SceneConfig(distortion=(0.1,))


@pytest.fixture(scope="module")
def plain_pair():
    """Three plain views without and with the lens (clean square corners)."""
    return (render_scene(SceneConfig(n_images=3, textured=False)),
            render_scene(SceneConfig(n_images=3, textured=False, distortion=LENS)))


def test_lens_scene_keeps_the_pinhole_cameras(plain_pair):
    pinhole, lens = plain_pair
    assert lens.distortion == LENS and lens.has_lens
    for i in range(3):
        np.testing.assert_array_equal(lens.P[i], pinhole.P[i])
        np.testing.assert_array_equal(lens.K[i], pinhole.K[i])
    X = lens.corners[lens.corner_visibility(0)]
    np.testing.assert_allclose(lens.project(0, X),
                               distort_pixels(project(lens.P[0], X), lens.K[0], LENS), atol=1e-12)
    np.testing.assert_array_equal(pinhole.project(0, X), project(pinhole.P[0], X))


def _corner_angles(scene, i):
    """(228,) interior angle (degrees) of each square corner in image i (distorted pixels)."""
    sq = scene.project(i, scene.corners).reshape(57, 4, 2)
    a, b = np.roll(sq, -1, axis=1) - sq, np.roll(sq, 1, axis=1) - sq
    cos = np.sum(a * b, axis=2) / np.linalg.norm(a, axis=2) / np.linalg.norm(b, axis=2)
    return np.degrees(np.arccos(np.clip(cos, -1, 1))).ravel()


@pytest.mark.parametrize("i", [0, 1, 2])
def test_lens_corners_land_on_the_rendered_corners(plain_pair, i):
    """The square corners' distorted pixels are where the rendered corners are (edge-line
    intersections, stereoseed.features.edge_corners); their pinhole pixels are not.

    Only corners of 60..120 degrees: at acute ones the two edges' profiles mix and the tool
    itself is off by up to ~0.9 px (without a lens too). On the others it is good to ~0.1 px
    (median) and ~0.4 px (worst), with or without the lens.
    """
    pinhole, lens = plain_pair
    for scene in (pinhole, lens):
        gray = to_gray(scene.images[i])
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
        angle = _corner_angles(scene, i)
        X = scene.corners[scene.corner_visibility(i) & (angle > 60) & (angle < 120)]
        truth = scene.project(i, X)
        found, ok = corners_on_edges(gray, gx, gy, truth)
        assert ok.sum() >= 40
        err = np.linalg.norm(found[ok] - truth[ok], axis=1)
        assert np.median(err) < 0.15 and np.percentile(err, 90) < 0.3 and err.max() < 0.5, err
    # The lens moves these corners by 0.3..1.3 px (the box is near the image centre); the
    # rendered corners follow the distorted pixels, not the pinhole ones.
    err_pinhole = np.linalg.norm(found[ok] - project(lens.P[i], X)[ok], axis=1)
    assert np.median(err_pinhole) > 2 * np.median(err)


@pytest.mark.parametrize("i", [0, 2])
def test_lens_dark_square_centroids_match_distorted_projection(plain_pair, i):
    """As test_dark_square_centroids_match_projection_subpixel, behind the lens: the coverage
    centroid of each rendered square is that of the square's outline (densely sampled) projected
    through the lens, to < 0.1 px."""
    _, scene = plain_pair
    grey = _grey(scene.images[i])
    squares = scene.corners.reshape(57, 4, 3)
    vis = scene.corner_visibility(i).reshape(57, 4).all(axis=1)
    s = np.linspace(0.0, 1.0, 40, endpoint=False)[:, None]
    errors, shifts = [], []
    for sq in squares[vis]:
        outline = np.concatenate([a + s * (b - a) for a, b in zip(sq, np.roll(sq, -1, axis=0))])
        found = _dark_square_centroid(grey, scene.project(i, outline))
        if found is None:
            continue
        expected, measured = found
        errors.append(np.linalg.norm(measured - expected))
        shifts.append(np.linalg.norm(project(scene.P[i], sq.mean(axis=0)) - expected))
    assert len(errors) >= 15
    assert np.max(errors) < 0.1
    assert np.max(shifts) > 0.5  # the lens did move the squares


def test_lens_image_is_the_pinhole_image_distorted(plain_pair, box_scene):
    _, lens = plain_pair
    K = lens.K[1]
    # The frame's corners look ~9-10 px further out (k1 = -0.12, barrel): the world point seen
    # at the bottom corners of the lens image projects there in the pinhole image.
    corners = np.array([[0.0, 479.0], [639.0, 479.0]])
    points, labels = lens.surface_points(1)
    assert np.all(labels[[479, 479], [0, 639]] >= 0)
    seen = points[[479, 479], [0, 639]]
    moved = project(lens.P[1], seen) - corners
    np.testing.assert_allclose(moved, undistort_pixels(corners, K, LENS) - corners, atol=1e-6)
    assert np.all((np.linalg.norm(moved, axis=1) > 8.0) & (np.linalg.norm(moved, axis=1) < 13))
    # Undistorting the (textured) lens image gives back the pinhole render up to resampling.
    textured = render_scene(SceneConfig(n_images=2, distortion=LENS)).images[1]
    back = undistort_image(textured, K, LENS)
    inner = (slice(20, 460), slice(20, 620))
    diff_back = np.abs(_grey(back) - _grey(box_scene.images[1]))[inner].mean()
    diff_raw = np.abs(_grey(textured) - _grey(box_scene.images[1]))[inner].mean()
    assert diff_back < 0.25 * diff_raw, (diff_back, diff_raw)


def test_lens_ground_truth_methods_use_distorted_pixels(plain_pair):
    _, lens = plain_pair
    # surface_points: the world point at each pixel centre projects back onto it.
    points, labels = lens.surface_points(0)
    hit = labels >= 0
    v, u = np.nonzero(hit)
    assert np.max(np.abs(lens.project(0, points[hit]) - np.stack([u, v], axis=1))) < 1e-6
    assert np.all(lens.is_visible(0, points[hit][::53]))
    # corner_visibility: inside the stored frame by the margin, in distorted pixels.
    vis = lens.corner_visibility(0)
    uv = lens.project(0, lens.corners[vis])
    assert np.all((uv >= 9.5) & (uv <= [640 - 10.5, 480 - 10.5]))
    # true_match: corners seen in image 0 at their distorted pixels -> distorted pixels in 1.
    both = vis & lens.corner_visibility(1)
    x1, ok = lens.true_match(0, 1, lens.project(0, lens.corners[both]))
    assert ok.mean() > 0.9
    np.testing.assert_allclose(x1[ok], lens.project(1, lens.corners[both])[ok], atol=1e-6)
    # calibration_points: distorted pixels plus the calibration noise.
    pattern, p1, p2 = lens.calibration_points()
    e = np.concatenate([p1 - lens.project(0, pattern), p2 - lens.project(1, pattern)])
    assert e.std() == pytest.approx(lens.config.calib_noise_px, rel=0.25)


def test_is_visible_rejects_points_a_lens_would_fold_into_the_frame():
    # A strong barrel lens maps far-off-axis directions back into the frame (r_d = r (1 - 0.3
    # r^2) falls again beyond r ~ 1.05); such points are not seen.
    scene = render_scene(SceneConfig(n_images=2, width=64, height=48, focal_px=80.0,
                                     focal0_px=80.0, supersample=1,
                                     distortion=(-0.3, 0.0, 0.0, 0.0)))
    R, t = scene.R[1], scene.t[1]
    xy = np.array([[1.6, 0.0], [0.2, 0.1]])  # normalized, pinhole
    X = (np.column_stack([xy, np.ones(2)]) * 0.3 - t) @ R  # 0.3 m in front, nothing between
    uv = scene.project(1, X)
    assert np.all((uv >= 0) & (uv <= [63, 47]))  # both distorted pixels fall in the frame
    np.testing.assert_array_equal(scene.is_visible(1, X), [False, True])


def test_write_scene_records_the_lens(plain_pair, tmp_path):
    pinhole, lens = plain_pair
    doc = json.loads(write_scene(lens, tmp_path / "lens")["cameras"].read_text())
    assert doc["distortion"] == list(LENS)
    assert "distortion" not in json.loads(
        write_scene(pinhole, tmp_path / "pin")["cameras"].read_text())


def test_a_scaled_config_sees_the_same_views_in_smaller_images():
    """SceneConfig.scaled: the same poses, the pixel geometry scaled (the quick paper bench's
    half-size images)."""
    from stereoseed.synthetic.scene import _cameras

    full = SceneConfig(n_images=4, seed=3)
    half = full.scaled(0.5)
    assert (half.width, half.height, half.n_images, half.seed) == (320, 240, 4, 3)
    assert SceneConfig().scaled(1.0) == SceneConfig()
    (Ks_f, Rs_f, ts_f), (Ks_h, Rs_h, ts_h) = _cameras(full), _cameras(half)
    for Kf, Kh, Rf, Rh, tf, th in zip(Ks_f, Ks_h, Rs_f, Rs_h, ts_f, ts_h):
        np.testing.assert_allclose(Rh, Rf)
        np.testing.assert_allclose(th, tf)
        np.testing.assert_allclose(Kh[:2, :2], 0.5 * Kf[:2, :2])
        # the principal point where the full image's falls, to a quarter pixel (the centre of
        # an image of even size sits half a pixel off its halved one's)
        np.testing.assert_allclose(Kh[:2, 2] + 0.5, 0.5 * (Kf[:2, 2] + 0.5), atol=0.25)
