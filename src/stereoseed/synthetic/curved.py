"""A curved rendered object: a textured sphere resting on a textured ground disk, seen by a ring of
cameras, with its exact surface (what the mesh of a curved object is judged against, where the
box's flat faces cannot show Poisson's smoothing of curvature).

The render casts rays analytically (sphere, then the plane z = 0), box-filters ``supersample``^2
samples per pixel and shades with a solid texture: a sum of 3D cosines of random directions
and wavelengths from a few pixels to tens of pixels (what Harris and ZNCC windows grip), so the
texture is continuous on the sphere without any parameterisation. Pixel (u, v) integer is a
pixel's centre, as everywhere in stereoseed. Camera i sits at azimuth ``azimuth0_deg + i *
step_deg``, elevation ``elevation_deg``, ``distance`` from the sphere's centre, looking at it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from stereoseed.geometry.projection import depths, project
from stereoseed.synthetic.scene import look_at
from stereoseed.validation import whole

__all__ = ["CurvedConfig", "CurvedScene", "render_curved"]

_WAVELENGTHS_M = (0.006, 0.04)  # the texture's shortest and longest wavelength (~4 to ~27 px at 1 m)
_COSINES = 32  # texture components: enough that no direction shows stripes
_SKY = 0.85  # the background's albedo, uniform: no feature there


@dataclass(frozen=True)
class CurvedConfig:
    n_images: int = 8
    step_deg: float = 20.0
    distance: float = 1.0  # metres, camera centre to the sphere's centre
    elevation_deg: float = 25.0
    radius: float = 0.15  # the sphere's radius (metres); it rests on the ground, centre at z = radius
    ground_radius: float = 0.6  # the textured ground disk's radius (beyond: a uniform floor)
    width: int = 640
    height: int = 480
    focal_px: float = 800.0
    supersample: int = 2
    azimuth0_deg: float = 30.0
    seed: int = 0

    def __post_init__(self) -> None:
        whole(self, "n_images", minimum=2)  # the stereo pair
        whole(self, "supersample")
        whole(self, "width", "height", minimum=16)
        if self.distance <= self.radius * 1.5:
            raise ValueError("CurvedConfig.distance must leave the cameras well outside the sphere")


@dataclass
class CurvedScene:
    """The rendered views: images (H, W, 3) uint8 BGR, names, K, R, t and P = K [R | t] per view."""

    config: CurvedConfig
    images: list[np.ndarray]
    names: list[str]
    K: list[np.ndarray]
    R: list[np.ndarray]
    t: list[np.ndarray]
    P: list[np.ndarray] = field(default_factory=list)

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.config.radius])

    @property
    def size(self) -> float:
        """The object's size: the sphere's diameter."""
        return 2.0 * self.config.radius

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (N,) of world points (N, 3) to the true surface: the sphere or the ground."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        sphere = np.abs(np.linalg.norm(points - self.centre, axis=1) - self.config.radius)
        return np.minimum(sphere, np.abs(points[:, 2]))

    def seen_sphere(self, views: list[int], n: int = 100_000, seed: int = 0) -> np.ndarray:
        """Samples (M, 3), uniform by area, of the sphere's surface that both cameras of one
        consecutive pair of ``views`` see (front-facing to both, inside both images): what the
        dense stage could have matched. A convex object hides nothing of itself that faces a
        camera, and the cameras stand above the ground."""
        d = np.random.default_rng(seed).normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        points = self.centre + self.config.radius * d
        points = points[points[:, 2] > 1e-3]  # the contact point with the ground: nothing to see
        seen = np.zeros(len(points), bool)
        for a, b in zip(views[:-1], views[1:]):
            seen |= self._sees(a, points) & self._sees(b, points)
        return points[seen]

    def _sees(self, i: int, points: np.ndarray) -> np.ndarray:
        centre = -self.R[i].T @ self.t[i]
        normal = (points - self.centre) / self.config.radius
        facing = np.einsum("ij,ij->i", normal, centre - points) > 0
        uv = project(self.P[i], points)
        inside = (uv >= 0).all(axis=1) & (uv[:, 0] <= self.config.width - 1) & (uv[:, 1] <= self.config.height - 1)
        return facing & (depths(self.P[i], points) > 0) & inside


def _solid_texture(points: np.ndarray, seed: int) -> np.ndarray:
    """Unit-variance band-limited noise (N,) at world points (N, 3)."""
    rng = np.random.default_rng([seed, 7])
    directions = rng.normal(size=(_COSINES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    wavelengths = np.exp(rng.uniform(*np.log(_WAVELENGTHS_M), size=_COSINES))
    phase = rng.uniform(0, 2 * np.pi, size=_COSINES)
    waves = (points @ (directions / wavelengths[:, None]).T) * (2 * np.pi) + phase
    return np.cos(waves).sum(axis=1) * math.sqrt(2.0 / _COSINES)


def _shade(o: np.ndarray, d: np.ndarray, cfg: CurvedConfig) -> np.ndarray:
    """Grey level in [0, 1] seen along rays o + t d (d (N, 3) unit)."""
    c = np.array([0.0, 0.0, cfg.radius])
    oc = o - c
    b = d @ oc
    disc = b * b - (oc @ oc - cfg.radius ** 2)
    t_sphere = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_sphere = np.where(t_sphere > 0, t_sphere, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)
    out = np.full(len(d), _SKY)
    on_sphere = t_sphere < t_ground
    hit = o + d * np.where(on_sphere, t_sphere, t_ground)[:, None]
    light = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    s = on_sphere
    normal = (hit[s] - c) / cfg.radius
    out[s] = (0.6 + 0.12 * _solid_texture(hit[s], cfg.seed)).clip(0.3, 0.95) * (0.55 + 0.45 * np.maximum(normal @ light, 0))
    g = ~on_sphere & np.isfinite(t_ground)
    disk = g & (hit[:, 0] ** 2 + hit[:, 1] ** 2 <= cfg.ground_radius ** 2)
    out[disk] = (0.5 + 0.12 * _solid_texture(hit[disk], cfg.seed + 1)).clip(0.2, 0.85) * (0.55 + 0.45 * light[2])
    out[g & ~disk] = 0.45
    return out


def render_curved(cfg: CurvedConfig = CurvedConfig()) -> CurvedScene:
    """The ring of views of :class:`CurvedConfig` rendered (grey images as BGR)."""
    target = np.array([0.0, 0.0, cfg.radius])
    cx, cy = (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0
    K = np.array([[cfg.focal_px, 0, cx], [0, cfg.focal_px, cy], [0, 0, 1.0]])
    s = cfg.supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    v, u = np.mgrid[0:cfg.height, 0:cfg.width].astype(np.float64)
    scene = CurvedScene(cfg, [], [], [], [], [])
    for i in range(cfg.n_images):
        az, el = math.radians(cfg.azimuth0_deg + i * cfg.step_deg), math.radians(cfg.elevation_deg)
        centre = target + cfg.distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                   math.sin(el)])
        R = look_at(centre, target)
        t = -R @ centre
        Minv = R.T @ np.linalg.inv(K)
        total = np.zeros(u.size)
        for dv in offsets:
            for du in offsets:
                pix = np.stack([u.ravel() + du, v.ravel() + dv, np.ones(u.size)], axis=1)
                d = pix @ Minv.T
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                total += _shade(centre, d, cfg)
        grey = np.clip(np.rint(total.reshape(u.shape) / s ** 2 * 255), 0, 255).astype(np.uint8)
        scene.images.append(np.repeat(grey[:, :, None], 3, axis=2))
        scene.names.append(f"sphere_{i:02d}.png")
        scene.K.append(K)
        scene.R.append(R)
        scene.t.append(t)
        scene.P.append(K @ np.c_[R, t])
    return scene
