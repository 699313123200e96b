"""Render a planar-faced calibration target (e.g. ChArUco boards on box faces) seen by a camera.

The target is described by ``target.json`` (written by the target generator)::

    {"unit": "mm",
     "faces": [{"image": "face_0.png", "origin": [x, y, z], "u_axis": [..], "v_axis": [..]}, ...]}

The centre of pixel (u, v) of face image ``image`` (a PNG beside target.json) lies at
``origin + u * u_axis + v * v_axis`` in the target's frame; the face covers the pixels' squares,
``u in [-0.5, W - 0.5]``, ``v in [-0.5, H - 0.5]``, and its printed side is seen from the side
``-(u_axis x v_axis)`` points to (the side from which the image appears unmirrored). The camera
``K [R | t]`` maps the target's frame to pixels, t in the target's unit; pixel (0, 0) is the
centre of the top-left pixel. A lens (``distortion``, OpenCV's model, :mod:`stereoseed.geometry.lens`)
distorts the image: each (sub-)sample's ray is that of its undistorted pixel, so a target point X
appears at ``stereoseed.geometry.lens.project_distorted(K, R, t, distortion, X)``.

Each of ``supersample^2`` sub-samples per pixel (a box filter) casts its ray against every face
plane; a hit counts if it lies inside the face and the face's printed side is turned to the
camera; the nearest such hit wins and samples the face image bilinearly. Large face images (a
300 dpi A4 page is 2480 x 3508) are first area-averaged (``cv2.resize(INTER_AREA)``) to about 2
texels per screen pixel along each axis where the face is seen largest, with the face's mapping
adjusted exactly (new pixel centre (u', v') = old ``((u' + 0.5) s_u - 0.5, (v' + 0.5) s_v - 0.5)``
for scale factors ``s = old size / new size``), so a view of the whole target is not aliased.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numba import njit, prange

from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_image
from stereoseed.geometry.lens import lens_coefficients, principal_r2, undistort_pixel_centre, undistort_sample
from stereoseed.synthetic.render import add_noise

__all__ = ["TargetFace", "Target", "load_target", "face_points", "render_target",
           "default_background", "from_boards"]

_TEXELS_PER_PIXEL = 2.0  # face texels per screen pixel kept by the pre-downscale
_STREAM_BACKGROUND, _STREAM_NOISE = 1, 2


@dataclass(frozen=True)
class TargetFace:
    """One face: image (H, W, 3) uint8 BGR; origin, u_axis, v_axis (3,) float64 (contract)."""

    name: str
    image: np.ndarray
    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray

    @property
    def printed_normal(self) -> np.ndarray:
        """Unit normal (3,) pointing to the side the print is seen from: -(u x v)."""
        n = -np.cross(self.u_axis, self.v_axis)
        return n / np.linalg.norm(n)


@dataclass(frozen=True)
class Target:
    """A loaded target.json: its unit and faces (load once, render many views)."""

    unit: str
    faces: tuple[TargetFace, ...]
    path: Path | None = None


def _vector(value, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise StereoseedError(f"{where}: needs 3 finite numbers, got {value!r}")
    return v


def load_target(path: str | os.PathLike) -> Target:
    """Read target.json and its face images. -> Target. Raises StereoseedError naming the file
    on a malformed description, a missing image or degenerate axes."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StereoseedError(f"{path}: target description not found; check the path") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StereoseedError(f"{path}: not a readable target.json ({e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("faces"), list) or not doc["faces"]:
        raise StereoseedError(f'{path}: needs {{"unit": ..., "faces": [{{"image", "origin", '
                              f'"u_axis", "v_axis"}}, ...]}} with at least one face')
    faces = []
    for k, f in enumerate(doc["faces"]):
        where = f"{path}: faces[{k}]"
        if not isinstance(f, dict) or not isinstance(f.get("image"), str):
            raise StereoseedError(f'{where}: needs "image" (a file name) and "origin", "u_axis", '
                                  f'"v_axis"')
        origin = _vector(f.get("origin"), f"{where}.origin")
        u = _vector(f.get("u_axis"), f"{where}.u_axis")
        v = _vector(f.get("v_axis"), f"{where}.v_axis")
        if np.linalg.norm(np.cross(u, v)) <= 1e-12 * np.linalg.norm(u) * np.linalg.norm(v) or \
                not np.linalg.norm(u) > 0 or not np.linalg.norm(v) > 0:
            raise StereoseedError(f"{where}: u_axis and v_axis must be non-zero and not parallel")
        image = read_image(path.parent / f["image"])
        faces.append(TargetFace(f["image"], image, origin, u, v))
    return Target(str(doc.get("unit", "")), tuple(faces), path)


def from_boards(boards, texels_per_square: int = 40, margin_squares: float = 1.0,
                poses: list[tuple[np.ndarray, np.ndarray]] | None = None) -> Target:
    """A renderable target from a calibration target's description
    (:class:`stereoseed.calibration.target.Target`, its faces' images not needed): each face's
    ChArUco board drawn by OpenCV at ``texels_per_square`` texels a square, with a white margin of
    ``margin_squares`` squares, placed where the description puts it, or moved by ``poses[k]`` =
    (R, t) (X -> R X + t: a target assembled other than described, its truth known)."""
    faces = []
    for k, f in enumerate(boards.faces):
        b = f.board
        nx, ny = b.squares
        m = int(round(margin_squares * texels_per_square))
        grey = np.full((ny * texels_per_square + 2 * m, nx * texels_per_square + 2 * m), 255, np.uint8)
        grey[m:m + ny * texels_per_square, m:m + nx * texels_per_square] = b.cv_board().generateImage(
            (nx * texels_per_square, ny * texels_per_square), marginSize=0, borderBits=1)
        # texel (a, b) is centred on the board's (u, v) = origin_uv + step ((a, b) - m + 0.5)
        step = b.square_px / texels_per_square
        uv0 = np.asarray(b.origin_uv, np.float64) + step * (0.5 - m)
        origin, u, v = f.origin + uv0[0] * f.u_axis + uv0[1] * f.v_axis, step * f.u_axis, step * f.v_axis
        if poses is not None:
            R, t = (np.asarray(a, np.float64) for a in poses[k])
            origin, u, v = R @ origin + t, R @ u, R @ v
        faces.append(TargetFace(f"face_{k}", cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), origin, u, v))
    return Target(boards.unit, tuple(faces), None)


def face_points(face: TargetFace, uv: np.ndarray) -> np.ndarray:
    """Target-frame points (N, 3) of face-image positions uv (N, 2) (pixel centres at integers;
    a square's corner between pixels is at half-integers)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    return face.origin + uv[:, :1] * face.u_axis + uv[:, 1:] * face.v_axis


def default_background(size: tuple[int, int], seed: int = 0) -> np.ndarray:
    """Mid-grey with a faint smooth texture (std ~4 grey levels, blobs of ~10 px):
    (H, W, 3) float64 on the 0..255 scale, seeded."""
    width, height = size
    rng = np.random.default_rng([seed, _STREAM_BACKGROUND])
    noise = cv2.GaussianBlur(rng.standard_normal((height, width)), (0, 0), 4.0,
                             borderType=cv2.BORDER_REFLECT)
    grey = 128.0 + 4.0 * noise / max(float(noise.std()), 1e-12)
    return np.repeat(grey[:, :, None], 3, axis=2)


def _background(background, size: tuple[int, int], seed: int) -> np.ndarray:
    width, height = size
    if background is None:
        return default_background(size, seed)
    bg = np.asarray(background, dtype=np.float64)
    if bg.ndim == 0 or bg.shape == (3,):
        return np.broadcast_to(bg, (height, width, 3)).copy()
    if bg.shape == (height, width):
        return np.repeat(bg[:, :, None], 3, axis=2)
    if bg.shape == (height, width, 3):
        return bg.copy()
    raise ValueError(f"background must be a grey level, a BGR triple or an image of "
                     f"{height} x {width} (x 3), got shape {bg.shape}")


def _texel_footprint(face: TargetFace, K, R, t) -> tuple[float, float]:
    """Largest on-screen length (px, pinhole) of one face texel along u and along v, over a 9 x 9
    grid of the face's points in front of the camera (0, 0 if none is)."""
    h, w = face.image.shape[:2]
    a, b = np.meshgrid(np.linspace(-0.5, w - 0.5, 9), np.linspace(-0.5, h - 0.5, 9))
    X = face_points(face, np.column_stack([a.ravel(), b.ravel()]))
    Xc = X @ R.T + t
    front = Xc[:, 2] > 1e-9 * np.abs(Xc).max()
    if not front.any():
        return 0.0, 0.0
    Xc = Xc[front]
    z = Xc[:, 2:3]
    out = []
    for axis in (face.u_axis, face.v_axis):
        d = R @ axis  # derivative of the camera point along the face axis
        dxy = (d[:2] * z - Xc[:, :2] * d[2]) / z**2  # of the normalized point
        dpix = dxy @ K[:2, :2].T
        out.append(float(np.linalg.norm(dpix, axis=1).max()))
    return out[0], out[1]


def _mip_face(face: TargetFace, K, R, t):
    """The face image area-averaged to about _TEXELS_PER_PIXEL texels per screen pixel (never
    enlarged) and its exactly adjusted (origin, u_axis, v_axis)."""
    h, w = face.image.shape[:2]
    fu, fv = _texel_footprint(face, K, R, t)
    new_w = min(w, max(2, int(np.ceil(w * fu * _TEXELS_PER_PIXEL)))) if fu > 0 else w
    new_h = min(h, max(2, int(np.ceil(h * fv * _TEXELS_PER_PIXEL)))) if fv > 0 else h
    if (new_w, new_h) == (w, h):
        return face.image, face.origin, face.u_axis, face.v_axis
    image = cv2.resize(face.image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    su, sv = w / new_w, h / new_h
    origin = face.origin + (0.5 * su - 0.5) * face.u_axis + (0.5 * sv - 0.5) * face.v_axis
    return image, origin, su * face.u_axis, sv * face.v_axis


@njit(cache=True)
def _sample_face(tex, offset, w, h, a, b, out):
    """Bilinear sample (edges replicated) of the face image stored row-major at tex[offset:]
    (w x h pixels, 3 channels) at (a, b); adds it to out (3,)."""
    a = min(max(a, 0.0), w - 1.0)
    b = min(max(b, 0.0), h - 1.0)
    a0 = min(int(a), w - 2) if w > 1 else 0
    b0 = min(int(b), h - 2) if h > 1 else 0
    fa = a - a0
    fb = b - b0
    a1 = min(a0 + 1, w - 1)
    b1 = min(b0 + 1, h - 1)
    i00 = offset + b0 * w + a0
    i01 = offset + b0 * w + a1
    i10 = offset + b1 * w + a0
    i11 = offset + b1 * w + a1
    for c in range(3):
        top = tex[i00, c] * (1.0 - fa) + tex[i01, c] * fa
        bottom = tex[i10, c] * (1.0 - fa) + tex[i11, c] * fa
        out[c] += top * (1.0 - fb) + bottom * fb


@njit(parallel=True, cache=True)
def _target_kernel(Kinv, Rt, C, lens, r2_max, has_lens, height_px, width_px, ss, origins, normals,
                   u_axes, v_axes, gram_inv, sizes, offsets, tex, background):
    """Supersampled render of the faces over background (H, W, 3) -> (H, W, 3) float64, 0..255.

    Face f: plane through origins[f] with normal u x v (normals[f], not normalised); the hit's
    face coordinates come from gram_inv[f] (2, 2) = inverse Gram matrix of (u, v)."""
    out = np.empty((height_px, width_px, 3), dtype=np.float64)
    n_faces = origins.shape[0]
    inv = 1.0 / (ss * ss)
    for v in prange(height_px):
        acc = np.zeros(3)
        for u in range(width_px):
            acc[0] = 0.0
            acc[1] = 0.0
            acc[2] = 0.0
            hits = 0
            xdc = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
            ydc = Kinv[1, 0] * u + Kinv[1, 1] * v + Kinv[1, 2]
            centre_ok = False
            xc = yc = jxx = jxy = jyy = det = 0.0
            if has_lens:
                xc, yc, jxx, jxy, jyy, det, centre_ok = undistort_pixel_centre(xdc, ydc, lens, r2_max)
            for j in range(ss):
                vs = v + (j + 0.5) / ss - 0.5
                for i in range(ss):
                    us = u + (i + 0.5) / ss - 0.5
                    x = Kinv[0, 0] * us + Kinv[0, 1] * vs + Kinv[0, 2]
                    y = Kinv[1, 0] * us + Kinv[1, 1] * vs + Kinv[1, 2]
                    if has_lens:
                        x, y, ok = undistort_sample(x, y, xdc, ydc, xc, yc, jxx, jxy, jyy, det, centre_ok, lens,
                                                    r2_max)
                        if not ok:
                            continue  # no ray: background
                    dx = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2]
                    dy = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2]
                    dz = Rt[2, 0] * x + Rt[2, 1] * y + Rt[2, 2]
                    best = np.inf
                    best_f = -1
                    best_a = 0.0
                    best_b = 0.0
                    for f in range(n_faces):
                        nd = normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz
                        if not nd > 0.0:  # printed side turned away (or ray in the plane)
                            continue
                        ox = origins[f, 0] - C[0]
                        oy = origins[f, 1] - C[1]
                        oz = origins[f, 2] - C[2]
                        s = (ox * normals[f, 0] + oy * normals[f, 1] + oz * normals[f, 2]) / nd
                        if not (s > 0.0 and s < best):
                            continue
                        px = s * dx - ox  # hit - origin
                        py = s * dy - oy
                        pz = s * dz - oz
                        pu = px * u_axes[f, 0] + py * u_axes[f, 1] + pz * u_axes[f, 2]
                        pv = px * v_axes[f, 0] + py * v_axes[f, 1] + pz * v_axes[f, 2]
                        a = gram_inv[f, 0, 0] * pu + gram_inv[f, 0, 1] * pv
                        b = gram_inv[f, 1, 0] * pu + gram_inv[f, 1, 1] * pv
                        if a < -0.5 or a > sizes[f, 0] - 0.5 or b < -0.5 or b > sizes[f, 1] - 0.5:
                            continue
                        best, best_f, best_a, best_b = s, f, a, b
                    if best_f >= 0:
                        _sample_face(tex, offsets[best_f], sizes[best_f, 0], sizes[best_f, 1],
                                     best_a, best_b, acc)
                        hits += 1
            miss = ss * ss - hits
            for c in range(3):
                out[v, u, c] = (acc[c] + miss * background[v, u, c]) * inv
    return out


def render_target(target: str | os.PathLike | Target, K: np.ndarray, R: np.ndarray,
                  t: np.ndarray, size: tuple[int, int] = (640, 480), distortion=(),
                  supersample: int = 3, background=None, noise_sigma: float = 0.0,
                  seed: int = 0) -> np.ndarray:
    """The image (H, W, 3) uint8 BGR of the target seen by camera K [R | t] behind a lens.

    target: path of target.json or a :class:`Target` (:func:`load_target`, to render many views
    without reading the images again). K (3, 3) (skew allowed), R (3, 3), t (3,) in the target's
    unit; size = (width, height); distortion: () or OpenCV's (k1, k2, p1, p2[, k3]);
    supersample: s x s box-filtered samples per pixel; background: None (mid-grey with a faint
    texture, :func:`default_background`), a grey level, a BGR triple or an (H, W[, 3]) image,
    0..255; noise_sigma: Gaussian grey-level noise (0..255 scale,
    :func:`stereoseed.synthetic.render.add_noise`), seeded by seed like the default background.
    """
    if not isinstance(target, Target):
        target = load_target(target)
    if supersample < 1:
        raise ValueError("supersample must be >= 1")
    width, height = int(size[0]), int(size[1])
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).ravel()
    lens = lens_coefficients(distortion)
    bg = _background(background, (width, height), seed)

    origins, normals, u_axes, v_axes, grams, sizes, offsets, texes = [], [], [], [], [], [], [], []
    offset = 0
    for face in target.faces:
        image, origin, u, v = _mip_face(face, K, R, t)
        h, w = image.shape[:2]
        origins.append(origin)
        normals.append(np.cross(u, v))  # the printed side faces -normal: rays with d.n > 0
        u_axes.append(u)
        v_axes.append(v)
        grams.append(np.linalg.inv([[u @ u, u @ v], [u @ v, v @ v]]))
        sizes.append((w, h))
        offsets.append(offset)
        texes.append(image.reshape(-1, 3))
        offset += w * h
    rgb = _target_kernel(
        np.ascontiguousarray(np.linalg.inv(K)), np.ascontiguousarray(R.T), -R.T @ t, lens,
        principal_r2(lens), bool(np.any(lens)), height, width, int(supersample),
        np.array(origins), np.array(normals), np.array(u_axes), np.array(v_axes),
        np.array(grams), np.array(sizes, dtype=np.int64), np.array(offsets, dtype=np.int64),
        np.ascontiguousarray(np.concatenate(texes)), np.ascontiguousarray(bg),
    )
    image = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if noise_sigma > 0:
        image = add_noise(image, noise_sigma, np.random.default_rng([seed, _STREAM_NOISE]))
    return image
