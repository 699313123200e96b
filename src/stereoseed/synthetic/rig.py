"""A stereo rig walked round the synthetic box: both cameras at every station, exact ground truth.

The scene is :mod:`stereoseed.synthetic.scene`'s (metres, z up; the textured box or the paper's
plain pattern box), rendered by the same kernels. At station k the first (left) camera stands
where image k of a ring of ``stations`` views ``step_deg`` apart would (:class:`SceneConfig`'s
placement and jitter); the second (right) camera sits ``baseline`` metres along the left camera's
x axis (image right, which is also the walking direction), turned in towards the left camera's
axis by ``toe_in_deg`` about its y axis, with a focal length ``focal_ratio`` times the left's. The
two cameras are different physical cameras: the left one's principal point is off centre by
``SceneConfig.principal_offset0_px`` (as the ring's camera 0), the right one's is centred.

:func:`render_rig` returns a :class:`RigScene`: its ``scene`` is a :class:`SyntheticScene` of the
2 x stations images, station k's left image at index 2k and its right one at 2k + 1 (so images 0
and 1 are the calibrated pair, as in every synthetic scene, and ``scene.calibration_points()``
is what a calibration of the first station measures); ``single_camera_walk()`` is the paper's
setting over the same images: the first station's pair, then the right camera's images of
stations 1 .. n-1.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from stereoseed.estimators.calibration import CalibrationResult, calibrate_camera
from stereoseed.estimators.rig_resection import Rig
from stereoseed.geometry.projection import compose_projection
from stereoseed.synthetic import scene as box
from stereoseed.synthetic.scene import SceneConfig, SyntheticScene, box_corners, render_views
from stereoseed.validation import positive, whole

__all__ = ["RigConfig", "RigScene", "render_rig", "rig_of"]


@dataclass(frozen=True)
class RigConfig:
    """A rig walked round the box (module docstring). ``view`` gives the rest: image size, the
    left camera's focal length (``focal_px``) and principal-point offset
    (``principal_offset0_px``), distance, elevation, look-at height, first azimuth, pose jitter,
    supersampling, seed, lens, texture amplitude and the calibration's pixel noise; its
    ``n_images``, ``step_deg``, ``noise_sigma``, ``textured``, ``focal0_px`` and ``focal_jitter``
    are not used (the fields here say those)."""

    baseline: float = 0.12  # metres (the scene's unit): a 12 cm bar (issue #38)
    toe_in_deg: float = 5.0  # the right camera turned in: its axis meets the left's ~1.4 m ahead
    focal_ratio: float = 1.03  # the right camera's focal length over the left's
    step_deg: float = 30.0  # azimuth between stations
    stations: int = 12
    noise_sigma: float = 0.0  # Gaussian grey-level noise of every image (0..255 scale)
    textured: bool = True  # False: the paper's plain box (uniform faces and dark squares)
    view: SceneConfig = field(default_factory=SceneConfig)

    def __post_init__(self) -> None:
        positive(self, "baseline", "focal_ratio")
        whole(self, "stations")
        if not 0.0 <= self.toe_in_deg < 45.0:
            raise ValueError(f"RigConfig.toe_in_deg must be within [0, 45), got {self.toe_in_deg!r}")
        if not self.noise_sigma >= 0.0:
            raise ValueError(f"RigConfig.noise_sigma must be >= 0, got {self.noise_sigma!r}")

    @property
    def scene_config(self) -> SceneConfig:
        """The SceneConfig the images are rendered with: ``view`` with this rig's 2 x stations
        images, noise and texture (its ring fields do not describe these cameras)."""
        return replace(self.view, n_images=2 * self.stations, step_deg=self.step_deg,
                       noise_sigma=self.noise_sigma, textured=self.textured)


def rig_of(config: RigConfig) -> Rig:
    """The true rig of ``config``: K_left, K_right and the right camera's pose in the left's frame."""
    view = config.view
    cx, cy = (view.width - 1) / 2.0, (view.height - 1) / 2.0
    f = view.focal_px
    dx, dy = view.principal_offset0_px
    K_left = np.array([[f, 0.0, cx + dx], [0.0, f, cy + dy], [0.0, 0.0, 1.0]])
    K_right = np.array([[f * config.focal_ratio, 0.0, cx], [0.0, f * config.focal_ratio, cy], [0.0, 0.0, 1.0]])
    a = math.radians(config.toe_in_deg)
    # rows: the right camera's axes in the left camera's frame; its optical axis turned towards -x
    R_rl = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    centre = np.array([config.baseline, 0.0, 0.0])  # the right camera's centre in the left's frame
    return Rig(K_left, K_right, R_rl, -R_rl @ centre)


@dataclass(eq=False)  # holds arrays: identity equality only
class RigScene:
    """Rendered rig images and exact ground truth (:func:`render_rig`).

    config: the RigConfig; scene: the 2 x stations images and their true cameras (station k's
    left image 2k, right 2k + 1; corners, surface and visibility queries as every synthetic
    scene); rig: the true rig (every station's pair has exactly its relative pose).
    """

    config: RigConfig
    scene: SyntheticScene
    rig: Rig = field(repr=False)

    @property
    def stations(self) -> int:
        return self.scene.n_images // 2

    def images(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Station k's (left, right) images."""
        return self.scene.images[2 * k], self.scene.images[2 * k + 1]

    def projections(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Station k's true (P_left, P_right)."""
        return self.scene.P[2 * k], self.scene.P[2 * k + 1]

    def calibration(self) -> tuple[CalibrationResult, CalibrationResult]:
        """The first station's pair as a calibration gives it: each camera calibrated (DLT + LM)
        from the pattern corners both images show, measured with ``view.calib_noise_px`` of noise
        (``scene.calibration_points()``)."""
        pattern, points1, points2 = self.scene.calibration_points()
        return (calibrate_camera(pattern, points1, what="rig station 1, left image"),
                calibrate_camera(pattern, points2, what="rig station 1, right image"))

    def calibrated_rig(self) -> Rig:
        """The rig as the first station's calibration gives it (:meth:`calibration`)."""
        left, right = self.calibration()
        return Rig.from_projections(left.P, right.P)

    def single_camera_walk(self) -> SyntheticScene:
        """The paper's setting over the same images: the first station's pair (images 0 and 1),
        then the right camera's images of stations 1 .. n-1 (images 2 .. n): the moving camera is
        the rig's right camera. Arrays are shared with ``scene``."""
        s = self.scene
        order = [0] + list(range(1, s.n_images, 2))
        pick = {k: [getattr(s, k)[i] for i in order] for k in ("images", "P", "K", "R", "t", "names")}
        return SyntheticScene(config=replace(s.config, n_images=len(order)), corners=s.corners,
                              corner_labels=s.corner_labels, **pick)


def render_rig(config: RigConfig = RigConfig()) -> RigScene:
    """Render the rig walked round the box (deterministic: same config, same bytes)."""
    # the ring's placement and jitter (a view depends on its index alone; a ring has 2 views at
    # least); its intrinsics are not the rig's
    ring = replace(config.view, n_images=max(config.stations, 2), step_deg=config.step_deg)
    _, R_left, t_left = (cams[:config.stations] for cams in box._cameras(ring))
    rig = rig_of(config)
    Ks, Rs, ts, names = [], [], [], []
    for k, (R, t) in enumerate(zip(R_left, t_left)):
        R_right, t_right = rig.right_pose(R, t)
        Ks += [np.array(rig.K_left), np.array(rig.K_right)]
        Rs += [R, R_right]
        ts += [t, t_right]
        names += [f"left_{k:03d}.png", f"right_{k:03d}.png"]
    cfg = config.scene_config
    images = render_views(cfg, Ks, Rs, ts)
    corners, labels = box_corners()
    scene = SyntheticScene(config=cfg, images=images, P=[compose_projection(K, R, t) for K, R, t in zip(Ks, Rs, ts)],
                           K=Ks, R=Rs, t=ts, corners=corners, names=names, corner_labels=labels)
    return RigScene(config=config, scene=scene, rig=rig)
