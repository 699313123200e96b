"""The paper's simulation target, rendered with exact ground truth.

A 34 x 34 x 44 cm box stands on the ground plane ``z = 0`` (world frame: metres, z up), centred on
the z axis: ``x, y in [-0.17, 0.17]``, ``z in [0, 0.44]``. Its five visible faces carry 57 dark
6 x 6 cm squares with 4 cm gaps: 3 columns x 4 rows on each side face, 3 x 3 on the top, hence
228 corners with exactly known 3D coordinates (the calibration pattern of the paper, section 5).

A ring of ``n_images`` views looks at the box: images 0 and 1 are the calibrated stereo pair (two
physically different cameras), images 1, 2, ... are the "moving camera", whose focal length varies
from image to image. Every image is ray cast (NumPy for the set-up, the Numba kernels of
:mod:`stereoseed.synthetic.render` for the per-sample work) with box-filtered supersampling, so
the ground truth (cameras, the world point seen through each pixel, visibility, the square
corners) is exact, not estimated. Design notes: ``docs/synthetic.md``.

Surface labels (used by :meth:`SyntheticScene.surface_points` and friends):

====  =================================  =====================================
 -1   background (sky; ray hits nothing)
  0   ground plane ``z = 0``
  1   side face ``x = +0.17``            outward normal +x
  2   side face ``y = +0.17``            outward normal +y
  3   side face ``x = -0.17``            outward normal -x
  4   side face ``y = -0.17``            outward normal -y
  5   top face ``z = 0.44``              outward normal +z
====  =================================  =====================================

Each face f has a local 2D frame ``X = FACE_ORIGIN[f] + s * FACE_U[f] + r * FACE_V[f]`` with
``s, r >= 0``, ``FACE_U x FACE_V = normal``: on a side face ``FACE_V`` is +z and ``FACE_U`` points
to the right of a viewer standing outside; on the top ``FACE_U = +x``, ``FACE_V = +y``.

Corner order (``box_corners()``, ``SyntheticScene.corners``): faces 1..5 in label order; within a
face squares row-major (row = index along ``FACE_V``, bottom to top, then column along
``FACE_U``); within a square its 4 corners counter-clockwise seen from outside, starting at its
(min s, min r) corner: ``(s0, r0), (s1, r0), (s1, r1), (s0, r1)``. Square k owns corners
``4k .. 4k+3``; squares 0..47 are on the side faces (12 each), 48..56 on the top.

A lens (``SceneConfig.distortion``, :mod:`stereoseed.geometry.lens`) distorts every image; K, R, t, P stay
the pinhole cameras (``lens.undistort_image`` gives the images P explains). Methods taking or
returning pixels (``SyntheticScene.project``, ``surface_points``, ``is_visible``, ``true_match``,
``corner_visibility``, ``calibration_points``, ``write_scene``'s points) use the stored images'
(distorted) pixels.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from stereoseed.geometry.projection import camera_center, compose_projection, depths, project
from stereoseed.io.files import write_image, write_text
from stereoseed.geometry.lens import distort_pixels, lens_coefficients, principal_r2, undistort_pixels
from stereoseed.synthetic.render import cast_kernel, render_kernel, add_noise  # the sensor's noise lives with the renderer

__all__ = ["BOX_HALF", "BOX_HEIGHT", "SQUARE_SIZE", "SQUARE_GAP", "GROUND_RADIUS", "FACE_LABELS", "FACE_NORMALS",
           "FACE_ORIGIN", "FACE_U", "FACE_V", "SceneConfig", "SyntheticScene", "box_corners", "look_at",
           "render_scene", "write_scene"]

# ---- Fixed geometry of the target (paper section 5); not configurable because 228 corners is the
# paper's number and other modules' tests rely on it.
BOX_HALF = 0.17  # half of the 34 cm base side, metres
BOX_HEIGHT = 0.44
SQUARE_SIZE = 0.06
SQUARE_GAP = 0.04
GROUND_RADIUS = 1.0  # textured ground disk; beyond it a flat, featureless floor

FACE_LABELS = {-1: "background", 0: "ground", 1: "+x", 2: "+y", 3: "-x", 4: "-y", 5: "top"}
# Index 0 (the ground) is filled in so that label-indexed lookups need no offset.
FACE_NORMALS = np.array(
    [[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1]], dtype=np.float64
)
FACE_U = np.array(
    [[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0], [1, 0, 0]], dtype=np.float64
)
FACE_V = np.array(
    [[0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 1, 0]], dtype=np.float64
)
_h = BOX_HALF
FACE_ORIGIN = np.array(
    [[0, 0, 0], [_h, -_h, 0], [_h, _h, 0], [-_h, _h, 0], [-_h, -_h, 0], [-_h, -_h, BOX_HEIGHT]],
    dtype=np.float64,
)
# Face extent (s, r) and square grid (columns along s, rows along r), label-indexed.
_FACE_EXTENT = np.array([[0, 0]] + [[2 * _h, BOX_HEIGHT]] * 4 + [[2 * _h, 2 * _h]], dtype=float)
_FACE_GRID = np.array([[0, 0]] + [[3, 4]] * 4 + [[3, 3]], dtype=np.int64)
del _h

# Appearance. Half-Lambert shading ("wrapped" diffuse) keeps every face lit but at a different
# level, so the box edges stay visible from every side while no face goes black.
_LIGHT = np.array([0.6, -0.35, 1.0]) / np.linalg.norm([0.6, -0.35, 1.0])
_SHADE = 0.55 + 0.45 * (0.5 + 0.5 * FACE_NORMALS @ _LIGHT)  # (6,), label-indexed
# RGB tints: warm box, cool ground, neutral-ish far floor; the sky is a colour on its own.
_TINTS = np.array([[1.0, 0.88, 0.70], [0.72, 0.86, 1.0], [0.80, 0.82, 0.80]], dtype=np.float64)
_SKY_RGB = np.array([0.80, 0.88, 1.0], dtype=np.float64)
_FAR_GROUND_ALBEDO = 0.45
# Albedo = clip(mean + amplitude * z, lo, hi) for a unit-variance texture value z.
# Rows: box (light part), box squares (dark), ground disk.
_ALBEDO_TEXTURED = np.array(
    [[0.75, 0.10, 0.55, 0.95], [0.10, 0.025, 0.05, 0.15], [0.50, 0.12, 0.25, 0.80]]
)
_ALBEDO_PLAIN = np.array([[0.85, 0.0, 0.0, 1.0], [0.08, 0.0, 0.0, 1.0], [0.50, 0.0, 0.0, 1.0]])
_FACE_TEXEL = 0.001  # 1 mm texels: several per pixel at ~1.4 m, so the texture is never blocky
_GROUND_TEXEL = 0.002
# Octaves of band-limited noise (Gaussian blur sigma in metres, weight): blobs from ~1.5 px to
# ~10 px in the images, what Harris (3x3) and 5x5 / 11x11 ZNCC windows can grip.
_OCTAVES = ((0.0025, 1.0), (0.005, 0.9), (0.010, 0.7), (0.020, 0.5))

# Independent random streams, each seeded by (seed, stream[, image]) so that e.g. changing the
# noise level or the number of images does not move the cameras or the texture.
_STREAM_POSE, _STREAM_TEXTURE, _STREAM_NOISE, _STREAM_CALIB = 1, 2, 3, 4


@dataclass(frozen=True)
class SceneConfig:
    """Parameters of the rendered ring of views around the box.

    Camera i (i >= 0) sits at azimuth ``azimuth0_deg + i * step_deg`` around the z axis, at
    elevation ``elevation_deg`` above the horizontal and at ``distance`` metres **from its look-at
    point** ``(0, 0, look_at_height)`` (not from the z axis), then jittered if ``pose_jitter``.
    """

    n_images: int = 14  # paper section 5: 14 images
    step_deg: float = 20.0  # azimuth step between consecutive views
    distance: float = 1.4  # metres, camera centre to look-at point
    elevation_deg: float = 25.0
    width: int = 640
    height: int = 480
    focal_px: float = 800.0  # camera 1 (the moving camera's nominal focal length)
    focal_jitter: float = 0.10  # images >= 2: focal_px * (1 + U(-jitter, jitter))
    noise_sigma: float = 0.0  # Gaussian grey-level noise (0..255 scale), see synthetic_render.add_noise
    textured: bool = True  # False: the paper's plain box (uniform faces + dark squares)
    supersample: int = 3  # s x s box-filtered samples per pixel
    seed: int = 0
    calib_noise_px: float = 0.1  # noise on the "measured" calibration image points
    pose_jitter: bool = True  # elevation +-3 deg, distance +-5 cm, look-at +-2 cm, roll +-2 deg
    azimuth0_deg: float = 30.0  # camera 0 sees faces +x, +y and the top: non-coplanar corners
    look_at_height: float = 0.2  # roughly the box centre
    focal0_px: float = 780.0  # camera 0 is another physical camera ...
    principal_offset0_px: tuple[float, float] = (3.5, -2.5)  # ... and an off-centre principal pt
    distortion: tuple[float, ...] = ()  # every image's lens: () or (k1, k2, p1, p2[, k3])
    # textured scene: the albedo standard deviation of the box's light part and of the ground
    # disk (None: 0.10 and 0.12); 0.02 is a faint texture (a white object, few Harris corners)
    texture_amplitude: float | None = None

    def __post_init__(self) -> None:
        lens_coefficients(self.distortion)  # 0, 4 or 5 finite numbers, else ValueError
        if self.n_images < 2:
            raise ValueError("n_images must be >= 2 (the stereo pair)")
        if self.supersample < 1:
            raise ValueError("supersample must be >= 1")
        if not 0.0 <= self.focal_jitter < 1.0:
            raise ValueError("focal_jitter must be in [0, 1)")
        if self.texture_amplitude is not None and not 0.0 <= self.texture_amplitude <= 0.5:
            raise ValueError("texture_amplitude must be in [0, 0.5] (an albedo standard deviation) or None")

    def scaled(self, factor: float) -> SceneConfig:
        """The same views in images ``factor`` times the size: width, height, the focal lengths
        and camera 0's principal-point offset scaled, so the field of view is the same."""
        return replace(self, width=round(self.width * factor), height=round(self.height * factor),
                       focal_px=self.focal_px * factor, focal0_px=self.focal0_px * factor,
                       principal_offset0_px=tuple(o * factor for o in self.principal_offset0_px))


# ---- Ground-truth geometry -------------------------------------------------------------------


def box_corners() -> tuple[np.ndarray, np.ndarray]:
    """The 228 square corners in the documented order.

    Returns corners (228, 3) float64 world coordinates and labels (228,) int8 (face 1..5).
    """
    corners, labels = [], []
    for f in range(1, 6):
        n_cols, n_rows = _FACE_GRID[f]
        for row in range(n_rows):
            r0 = SQUARE_GAP + row * (SQUARE_SIZE + SQUARE_GAP)
            for col in range(n_cols):
                s0 = SQUARE_GAP + col * (SQUARE_SIZE + SQUARE_GAP)
                s1, r1 = s0 + SQUARE_SIZE, r0 + SQUARE_SIZE
                for s, r in ((s0, r0), (s1, r0), (s1, r1), (s0, r1)):
                    corners.append(FACE_ORIGIN[f] + s * FACE_U[f] + r * FACE_V[f])
                    labels.append(f)
    # Round away the 1e-17 residue of the sums: the corners are exact centimetre values.
    return np.round(np.array(corners), 12), np.array(labels, dtype=np.int8)


def look_at(center: np.ndarray, target: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """cam_from_world rotation (3, 3) looking from center to target, image y down ~ world -z."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])  # right of the viewer, horizontal
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # completes a right-handed frame pointing down
    R = np.stack([x, y, z])
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll @ R


def _cameras(cfg: SceneConfig) -> tuple[list, list, list]:
    """K, R, t lists for the ring (see SceneConfig); one seeded stream per image."""
    cx, cy = (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0  # centre under the pixel convention
    Ks, Rs, ts = [], [], []
    for i in range(cfg.n_images):
        rng = np.random.default_rng([cfg.seed, _STREAM_POSE, i])
        # Always draw the same numbers in the same order, so pose_jitter=False changes only the
        # pose and the focal lengths stay those of the jittered ring.
        d_elev = np.radians(rng.uniform(-3.0, 3.0))
        d_dist = rng.uniform(-0.05, 0.05)
        d_look = rng.uniform(-0.02, 0.02, size=3)
        roll = np.radians(rng.uniform(-2.0, 2.0))
        focal_factor = 1.0 + rng.uniform(-cfg.focal_jitter, cfg.focal_jitter)
        if not cfg.pose_jitter:
            d_elev, d_dist, d_look, roll = 0.0, 0.0, np.zeros(3), 0.0

        if i == 0:
            dx0, dy0 = cfg.principal_offset0_px
            f, px, py = cfg.focal0_px, cx + dx0, cy + dy0
        elif i == 1:
            f, px, py = cfg.focal_px, cx, cy
        else:
            f, px, py = cfg.focal_px * focal_factor, cx, cy
        K = np.array([[f, 0.0, px], [0.0, f, py], [0.0, 0.0, 1.0]])

        az = np.radians(cfg.azimuth0_deg + i * cfg.step_deg)
        el = np.radians(cfg.elevation_deg) + d_elev
        target = np.array([0.0, 0.0, cfg.look_at_height]) + d_look
        direction = np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
        )
        center = target + (cfg.distance + d_dist) * direction
        if center[2] <= 0.0:
            raise ValueError("camera below the ground plane; raise elevation_deg")
        R = look_at(center, target, roll)
        Ks.append(K)
        Rs.append(R)
        ts.append(-R @ center)
    return Ks, Rs, ts


# ---- Textures --------------------------------------------------------------------------------


def _band_noise(shape: tuple[int, int], texel: float, rng: np.random.Generator) -> np.ndarray:
    """Multi-octave band-limited noise, zero mean, unit variance. -> (H, W) float32."""
    total = np.zeros(shape, dtype=np.float32)
    for sigma_m, weight in _OCTAVES:
        white = rng.standard_normal(shape).astype(np.float32)
        blurred = cv2.GaussianBlur(white, (0, 0), sigma_m / texel, borderType=cv2.BORDER_REFLECT)
        total += np.float32(weight) * blurred / blurred.std()
    total -= total.mean()
    return total / total.std()


def _textures(cfg: SceneConfig) -> tuple[np.ndarray, np.ndarray]:
    """Face textures (6, T, T) (label-indexed; index 0 unused) and ground texture (1, G, G).

    Side faces and the top share one square array size (the largest face) so that the kernel
    indexes a single 3D array. They depend on the seed alone: made once per seed (a third of
    a short scene's rendering time), each caller gets its own copy.
    """
    if not cfg.textured:
        # Albedo amplitudes are zero then; tiny arrays keep the kernel's code path unchanged.
        return np.zeros((6, 2, 2), np.float32), np.zeros((1, 2, 2), np.float32)
    faces, ground = _seeded_textures(cfg.seed)
    return faces.copy(), ground.copy()


@lru_cache(maxsize=2)
def _seeded_textures(seed: int) -> tuple[np.ndarray, np.ndarray]:
    n_face = int(round(BOX_HEIGHT / _FACE_TEXEL))
    n_ground = int(round(2 * GROUND_RADIUS / _GROUND_TEXEL))
    rng = np.random.default_rng([seed, _STREAM_TEXTURE])
    faces = np.zeros((6, n_face, n_face), np.float32)
    for f in range(1, 6):
        faces[f] = _band_noise((n_face, n_face), _FACE_TEXEL, rng)
    ground = _band_noise((n_ground, n_ground), _GROUND_TEXEL, rng)[None]
    return faces, ground


def _cast(C: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit along each ray. C (3,), dirs (N, 3) -> t (N,), labels (N,) int8."""
    dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    return cast_kernel(np.ascontiguousarray(C, dtype=np.float64), dirs, BOX_HALF, BOX_HEIGHT)


def _snap_to_surface(points: np.ndarray, labels: np.ndarray) -> None:
    """Set the coordinate fixed by each point's plane to its exact value (in place).

    Removes the ~1e-17 rounding of o + t d, so that e.g. ground points have z == 0 exactly.
    """
    fixed = {0: (2, 0.0), 1: (0, BOX_HALF), 2: (1, BOX_HALF), 3: (0, -BOX_HALF),
             4: (1, -BOX_HALF), 5: (2, BOX_HEIGHT)}
    for lab, (axis, value) in fixed.items():
        points[labels == lab, axis] = value


def noise_generator(scene_seed: int, index: int) -> np.random.Generator:
    """The random stream of image ``index``'s pixel noise in the scene of seed ``scene_seed``:
    noisy variants of a rendered scene can be made without rendering again."""
    return np.random.default_rng([scene_seed, _STREAM_NOISE, index])


# ---- The scene -------------------------------------------------------------------------------


@dataclass(eq=False)  # holds arrays: identity equality only
class SyntheticScene:
    """Rendered images and exact ground truth. Build it with :func:`render_scene`.

    images: list of (H, W, 3) uint8 BGR; P: list of (3, 4) = K [R | t]; K, R: lists of (3, 3);
    t: list of (3,); corners: (228, 3) world coordinates (module docstring: order);
    corner_labels: (228,) face label of each corner; names: "img_000.png", ...
    K, R, t, P: pinhole cameras; with a lens the images and pixel methods are distorted (module
    docstring).
    """

    config: SceneConfig
    images: list
    P: list
    K: list
    R: list
    t: list
    corners: np.ndarray
    names: list
    corner_labels: np.ndarray = field(default_factory=lambda: box_corners()[1])
    _surface_cache: dict = field(default_factory=dict, init=False, repr=False)

    @property
    def n_images(self) -> int:
        return len(self.images)

    def prefix(self, n: int) -> SyntheticScene:
        """The first n images: what :func:`render_scene` gives with ``n_images=n`` (an image and
        its camera depend on their index alone), without rendering again; arrays are copies."""
        if not 1 <= n <= self.n_images:
            raise ValueError(f"a prefix of {n} images of a {self.n_images}-image scene")
        first = {k: [np.array(a, copy=True) for a in getattr(self, k)[:n]] for k in ("images", "P", "K", "R", "t")}
        return SyntheticScene(config=replace(self.config, n_images=n), corners=self.corners.copy(),
                              names=list(self.names[:n]), corner_labels=self.corner_labels.copy(), **first)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres (n_images, 3)."""
        return np.array([camera_center(P) for P in self.P])

    @property
    def distortion(self) -> tuple[float, ...]:
        """The lens of every image (``config.distortion``): () or (k1, k2, p1, p2[, k3])."""
        return tuple(self.config.distortion)

    @property
    def has_lens(self) -> bool:
        return bool(np.any(lens_coefficients(self.config.distortion)))

    def project(self, i: int, points: np.ndarray) -> np.ndarray:
        """Pixels in image i as stored (distorted when a lens is set) of world points (N, 3)
        -> (N, 2). Without a lens: ``project(P[i], points)``."""
        uv = project(self.P[i], points)
        if not self.has_lens:
            return uv
        return distort_pixels(uv, self.K[i], self.config.distortion)

    def _rays(self, i: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World ray directions (N, 3) (not normalised; t = 1 at depth 1) through pixels (u, v)
        of image i as stored (undistorted first when a lens is set; NaN where no ray exists)."""
        Minv = self.R[i].T @ np.linalg.inv(self.K[i])
        pix = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
        if self.has_lens:
            pix[:, :2] = undistort_pixels(pix[:, :2], self.K[i], self.config.distortion)
        return pix @ Minv.T

    def surface_points(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """World point seen through each pixel centre of image i (no supersampling).

        Returns points (H, W, 3) float64 (NaN on background) and labels (H, W) int8 (-1
        background, 0 ground, 1..5 box faces; module docstring). Cached; do not modify in place.
        """
        if i not in self._surface_cache:
            H, W = self.config.height, self.config.width
            v, u = np.mgrid[0:H, 0:W]
            dirs = self._rays(i, u.ravel(), v.ravel())
            C = camera_center(self.P[i])
            t, labels = _cast(C, dirs)
            labels[~np.all(np.isfinite(dirs), axis=1)] = -1  # beyond a lens's principal branch
            with np.errstate(invalid="ignore"):
                points = C + t[:, None] * dirs
            points[labels < 0] = np.nan
            _snap_to_surface(points, labels)
            self._surface_cache[i] = (points.reshape(H, W, 3), labels.reshape(H, W))
        return self._surface_cache[i]

    def is_visible(self, i: int, points: np.ndarray, margin: float = 0.0,
                   tol: float = 1e-6) -> np.ndarray:
        """Whether each world point is seen by camera i. points (N, 3) -> (N,) bool.

        Visible = in front of the camera, projecting inside the image shrunk by ``margin`` px
        (image area: ``-0.5 + margin <= u < W - 0.5 - margin``, likewise v), and not occluded:
        the first surface along the ray from the centre is not closer than ``1 - tol`` times the
        point's distance. Points in empty space count as visible if nothing hides them.
        With a lens the image area is that of the stored (distorted) image, and the point's
        distorted pixel must undistort back to it (a point far outside the frame that a strong
        lens would fold back in is not seen).
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cfg = self.config
        pinhole = project(self.P[i], points)
        uv = pinhole
        with np.errstate(invalid="ignore"):
            if self.has_lens:
                uv = distort_pixels(pinhole, self.K[i], cfg.distortion)
                back = undistort_pixels(uv, self.K[i], cfg.distortion)
                same = np.all(np.abs(back - pinhole) < 1e-6, axis=1)
            else:
                same = True
            inside = (
                (depths(self.P[i], points) > 0) & same
                & (uv[:, 0] >= margin - 0.5) & (uv[:, 0] < cfg.width - 0.5 - margin)
                & (uv[:, 1] >= margin - 0.5) & (uv[:, 1] < cfg.height - 0.5 - margin)
            )
        C = camera_center(self.P[i])
        # Parametrise the ray so that t = 1 at the point itself: occluded iff a hit has t < 1.
        t, labels = _cast(C, points - C)
        return inside & ((labels < 0) | (t >= 1.0 - tol))

    def true_match(self, i: int, j: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact position in image j of the surface point seen at pixels x (N, 2) of image i.

        The surface label comes from the nearest pixel; points whose 3x3 neighbourhood spans two
        surfaces (edges, occlusion boundaries) or the background are not evaluated. The world
        point is the intersection of the ray through x with that face's plane (exact, no
        interpolation), kept if camera j sees it. Returns (N, 2) positions and (N,) bool
        "evaluable". With a lens, x and the positions are distorted pixels (images as stored).
        """
        x = np.asarray(x, np.float64).reshape(-1, 2)
        _, labels = self.surface_points(i)
        h, w = labels.shape
        u = np.clip(np.rint(x[:, 0]).astype(int), 1, w - 2)
        v = np.clip(np.rint(x[:, 1]).astype(int), 1, h - 2)
        lab = labels[v, u]
        nb = np.stack([labels[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
        ok = np.all(nb == lab[:, None], axis=1) & (lab >= 0)
        lab = np.where(ok, lab, 0)
        C = camera_center(self.P[i])
        rays = self._rays(i, x[:, 0], x[:, 1])
        n, o = FACE_NORMALS[lab], FACE_ORIGIN[lab]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("nk,nk->n", o - C, n) / np.einsum("nk,nk->n", rays, n)
        X = C + t[:, None] * rays
        ok &= np.isfinite(t) & (t > 0)
        ok[ok] &= self.is_visible(j, X[ok])
        return self.project(j, X), ok

    def corner_visibility(self, i: int, margin: float = 10.0) -> np.ndarray:
        """(228,) bool: corner's face turned towards camera i, unoccluded, >= margin px inside
        image i as stored (distorted with a lens)."""
        C = camera_center(self.P[i])
        facing = np.einsum("nk,nk->n", FACE_NORMALS[self.corner_labels], C - self.corners) > 0
        return facing & self.is_visible(i, self.corners, margin=margin)

    def sample_surface_points(self, n: int, rng: np.random.Generator,
                              include_ground: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """n points uniform by area on the textured surfaces. -> points (n, 3), labels (n,) int8.

        Surfaces: the 5 box faces and, if include_ground, the ground disk of radius
        GROUND_RADIUS minus the box footprint (label 0).
        """
        areas = [0.0] + [float(np.prod(_FACE_EXTENT[f])) for f in range(1, 6)]
        if include_ground:
            areas[0] = math.pi * GROUND_RADIUS**2 - (2 * BOX_HALF) ** 2
        p = np.array(areas) / sum(areas)
        labels = rng.choice(6, size=n, p=p).astype(np.int8)
        points = np.empty((n, 3))
        box = labels > 0
        s = rng.uniform(0.0, 1.0, size=(n, 2)) * _FACE_EXTENT[labels]
        points[box] = (FACE_ORIGIN[labels[box]] + s[box, :1] * FACE_U[labels[box]]
                       + s[box, 1:] * FACE_V[labels[box]])
        # Ground: uniform on the disk, rejecting the footprint; a few rounds suffice (~4 % loss).
        todo = np.flatnonzero(~box)
        while todo.size:
            r = GROUND_RADIUS * np.sqrt(rng.uniform(size=todo.size))
            a = rng.uniform(0.0, 2 * math.pi, size=todo.size)
            xy = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
            ok = np.any(np.abs(xy) > BOX_HALF, axis=1)
            points[todo[ok], :2] = xy[ok]
            points[todo[ok], 2] = 0.0
            todo = todo[~ok]
        _snap_to_surface(points, labels)
        return points, labels

    def calibration_points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a user would measure on the pattern with the stereo pair (images 0 and 1).

        Returns pattern (M, 3) corners visible in both images (corner order kept), points1 (M, 2)
        their pixels in image 0 and points2 (M, 2) in image 1 (distorted pixels with a lens: what
        one measures on the stored images), each with Gaussian noise of
        ``config.calib_noise_px`` (seeded; the same call always gives the same numbers).
        """
        both = self.corner_visibility(0) & self.corner_visibility(1)
        pattern = self.corners[both]
        rng = np.random.default_rng([self.config.seed, _STREAM_CALIB])
        sigma = self.config.calib_noise_px
        points1 = self.project(0, pattern) + rng.normal(0.0, sigma, size=(len(pattern), 2))
        points2 = self.project(1, pattern) + rng.normal(0.0, sigma, size=(len(pattern), 2))
        return pattern, points1, points2


def render_scene(config: SceneConfig = SceneConfig()) -> SyntheticScene:
    """Render the ring of views around the box (deterministic: same config, same bytes).

    With ``config.distortion`` each (sub-)sample of a pixel is undistorted through the lens
    before its ray is cast: the images are the pinhole images, distorted. Without one (or with
    all-zero coefficients) the pinhole kernel renders, byte for byte as before lenses existed.
    """
    Ks, Rs, ts = _cameras(config)
    corners, labels = box_corners()
    return SyntheticScene(config=config, images=render_views(config, Ks, Rs, ts),
                          P=[compose_projection(K, R, t) for K, R, t in zip(Ks, Rs, ts)], K=Ks, R=Rs, t=ts,
                          corners=corners, names=[f"img_{i:03d}.png" for i in range(config.n_images)],
                          corner_labels=labels)


def render_views(config: SceneConfig, Ks: list, Rs: list, ts: list) -> list[np.ndarray]:
    """The box scene of ``config`` (texture, lens, supersampling, noise) seen by the cameras
    K [R | t] given: (H, W, 3) uint8 BGR images, image i's noise from ``noise_generator(seed, i)``
    (:func:`render_scene` gives its ring's cameras; a rig gives its stations')."""
    cfg = config
    lens = lens_coefficients(cfg.distortion)
    r2_max = principal_r2(lens)
    tex_faces, tex_ground = _textures(cfg)
    albedo = _ALBEDO_TEXTURED if cfg.textured else _ALBEDO_PLAIN
    if cfg.textured and cfg.texture_amplitude is not None:
        albedo = albedo.copy()
        albedo[[0, 2], 1] = cfg.texture_amplitude
    tints, far_ground = _TINTS, _FAR_GROUND_ALBEDO
    if not cfg.textured:
        # The plain scene's ground is one uniform floor: no disk rim to offer a spurious feature.
        tints = _TINTS.copy()
        tints[2] = tints[1]
        far_ground = albedo[2, 0]
    scene_args = (
        cfg.height, cfg.width, cfg.supersample,
        BOX_HALF, BOX_HEIGHT, FACE_ORIGIN, FACE_U, FACE_V, _FACE_GRID, SQUARE_SIZE,
        SQUARE_GAP, tex_faces, _FACE_TEXEL, tex_ground, _GROUND_TEXEL, GROUND_RADIUS,
        albedo, _SHADE, tints, _SKY_RGB, far_ground,
    )
    images = []
    for i, (K, R, t) in enumerate(zip(Ks, Rs, ts)):
        Kinv = np.linalg.inv(K)
        rgb = render_kernel(np.ascontiguousarray(R.T @ Kinv), np.ascontiguousarray(Kinv),
                             np.ascontiguousarray(R.T), bool(np.any(lens)), np.asarray(lens, np.float64),
                             float(r2_max), -R.T @ t, *scene_args)
        image = np.clip(np.rint(rgb[:, :, ::-1] * 255.0), 0, 255).astype(np.uint8)  # RGB -> BGR
        if cfg.noise_sigma > 0:
            image = add_noise(image, cfg.noise_sigma, noise_generator(cfg.seed, i))
        images.append(np.ascontiguousarray(image))
    return images


def write_scene(scene: SyntheticScene, out_dir: str | os.PathLike) -> dict:
    """Write images and ground truth to out_dir (created if missing).

    Files: the PNG images (scene.names); ``cameras.json`` {"images": [{"name", "P", "K", "R",
    "t", "center"}]} (pinhole cameras), plus ``"distortion": [k1, k2, p1, p2(, k3)]`` at the top
    level when the scene has a lens; ``corners.txt`` (228 lines "X Y Z"); ``pattern.txt`` (M lines
    "X Y Z"), ``points1.txt`` / ``points2.txt`` (M lines "u v", images 0 / 1) from
    calibration_points() (distorted pixels with a lens);
    ``images.txt`` (image paths relative to out_dir, in order).
    Returns {"images": [Path, ...], "cameras", "corners", "pattern", "points1", "points2",
    "images_txt": Path}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict = {"images": []}
    for name, image in zip(scene.names, scene.images):
        written["images"].append(write_image(out / name, image))
    cams = [
        {"name": name, "P": P.tolist(), "K": K.tolist(), "R": R.tolist(),
         "t": np.asarray(t).tolist(), "center": camera_center(P).tolist()}
        for name, P, K, R, t in zip(scene.names, scene.P, scene.K, scene.R, scene.t)
    ]
    written["cameras"] = out / "cameras.json"
    cameras_doc: dict = {"images": cams}
    if scene.has_lens:
        cameras_doc["distortion"] = [float(c) for c in scene.distortion]
    write_text(written["cameras"], json.dumps(cameras_doc, indent=1))
    pattern, points1, points2 = scene.calibration_points()
    for key, array, fmt in (("corners", scene.corners, "%.10f"), ("pattern", pattern, "%.10f"),
                            ("points1", points1, "%.6f"), ("points2", points2, "%.6f")):
        written[key] = out / f"{key}.txt"
        np.savetxt(written[key], array, fmt=fmt)
    written["images_txt"] = out / "images.txt"
    write_text(written["images_txt"], "".join(f"{name}\n" for name in scene.names))
    return written
