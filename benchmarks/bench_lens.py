"""Calibration with the lens, end to end on rendered views of the product's own printed target
(issue 20): how well the calibrated camera + lens explains every pixel's true ray, from the pair
view alone and with 4 more views per camera, with and without image noise; and a 12-image object
ring rendered through the same lens, reconstructed with the calibrated distortion, without it,
and the same ring without a lens.

    python benchmarks/bench_lens.py          # prints JSON; also a section of make bench
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from stereoseed.config import Config
from stereoseed.experiments.evaluation import camera_errors
from stereoseed.geometry.projection import camera_center, compose_projection
from stereoseed.geometry.lens import project_distorted, undistort_image, undistort_pixels, undistortion_maps
from stereoseed.calibration.detection import detect_target
from stereoseed.calibration.rig import calibrate_cameras
from stereoseed.pipeline import reconstruct
from stereoseed.synthetic.scene import SceneConfig, render_scene
from stereoseed.synthetic.target import load_target as load_rendered_target
from stereoseed.synthetic.target import render_target
from stereoseed.calibration.printing import make_target
from stereoseed.calibration.target import load_target

LENS = (-0.12, 0.03, 0.001, -0.0005)
MM = 1000.0  # the target is in mm, the box scene in metres
DISTANCE = 1.0  # m: an A3 target's markers must cover a few pixels per cell in the pair's views
# the target's corner stands 0.42 m up in the scene (the height of the box), so that the pair,
# aimed at the box, sees it: X_target = MM * X_world - TARGET_AT
TARGET_AT = np.array([0.0, 0.0, 420.0])


def _look_at(centre: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = at - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def _lens_views(K: np.ndarray, around: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Poses (mm) from which the target falls in other parts of the frame: the camera ~0.55 m
    away, aimed 80-120 mm beside the target's corner."""
    out = []
    for i in range(n):
        a = np.radians(30.0 + 20.0 * (i - (n - 1) / 2))
        centre = around + np.array([750.0 * np.cos(a), 750.0 * np.sin(a), 450.0])
        aside = np.array([[130, -130, 90], [-130, 130, 90], [130, 130, -170], [-130, -130, -170]][i % 4], float)
        out.append(_look_at(centre, np.array([-140.0, -140.0, -170.0]) + aside))
    return out


def _frame_errors(cal, K_true: np.ndarray, R: np.ndarray, t: np.ndarray, covered: np.ndarray | None = None
                  ) -> np.ndarray:
    """Per pixel of a grid over the frame (or of the convex hull ``covered``): the distance
    between the pixel and the estimated camera + lens's image of a point on its true ray."""
    import cv2

    u, v = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    px = np.c_[u.ravel(), v.ravel()]
    if covered is not None:
        hull = cv2.convexHull(covered.astype(np.float32))
        px = px[[cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in px]]
    rays = undistort_pixels(px, K_true, LENS)
    Xc = np.c_[(rays - K_true[:2, 2]) / np.diag(K_true)[:2], np.ones(len(rays))] * 1400.0
    X = (Xc - t) @ R
    return np.linalg.norm(project_distorted(cal.K, cal.R[0], cal.t[0], cal.distortion, X) - px, axis=1)


class _Camera:
    """A calibrated camera as this benchmark reads it: K, distortion, the views' R, t (the pair's
    first) and RMS, P of the pair's view."""

    def __init__(self, cam):
        self.K, self.distortion, self.views = cam.K, cam.lens, [v for v in cam.views if v.used]
        self.R, self.t = [v.R for v in self.views], [v.t for v in self.views]
        self.rms_px = [v.rms_px for v in self.views]
        self.P = compose_projection(self.K, self.R[0], self.t[0])


def calibration(noise: float, scene, folder: Path) -> tuple[dict, list]:
    """Calibrate both cameras of the pair from renders of the target in ``folder`` (made once)."""
    target = load_target(folder / "target.json")
    texture = load_rendered_target(folder / "target.json")  # the face images read once for every render
    out = {}
    cals = []
    for cam in (0, 1):
        K, R = scene.K[cam], scene.R[cam]
        t = scene.t[cam] * MM + R @ TARGET_AT  # the pair's camera in the target's frame
        pair = render_target(texture, K, R, t, distortion=LENS, noise_sigma=noise, seed=cam)
        more = [render_target(texture, K, Rv, tv, distortion=LENS, noise_sigma=noise, seed=10 * cam + k)
                for k, (Rv, tv) in enumerate(_lens_views(K, np.zeros(3), 4))]
        for label, images in (("pair alone", [pair]), ("pair + 4 views", [pair] + more)):
            dets = [detect_target(im, target, what=f"view{k}") for k, im in enumerate(images)]
            cal = _Camera(calibrate_cameras(target, [dets], labels=[f"camera {cam + 1}"]).cameras[0])
            view = cal.views[0]
            under = np.linalg.norm(view.reprojected - project_distorted(K, R, t, LENS, view.detection.points3d), axis=1)
            C_true = camera_center(compose_projection(K, R, t))
            out[f"camera{cam + 1}/{label}"] = {
                "centre_error_pct_of_distance": float(100 * np.linalg.norm(camera_center(cal.P) - C_true)
                                                      / np.linalg.norm(C_true)),
                "target_points_p95_px": float(np.percentile(under, 95)),
                "covered_frame_p95_px": float(np.percentile(_frame_errors(cal, K, R, t, view.detection.pixels), 95)),
                "whole_frame_p95_px": float(np.percentile(_frame_errors(cal, K, R, t), 95)),
                "corners_per_view": [int(len(v.detection)) for v in cal.views], "rms_px": cal.rms_px,
                "distortion": cal.distortion.tolist()}
            if label == "pair + 4 views":
                cals.append(cal)
    return out, cals


def ring(cals) -> dict:
    """The 12-image ring through the lens, reconstructed with the calibrated lens (camera 2's for
    every walk image), without undistorting, and the same ring without a lens."""
    def errors(scene, images, P_pair):
        recon, report = reconstruct(images, scene.names, P_pair, Config())
        c = np.array([e for e in camera_errors([v.P_input for v in recon.views], scene.P)["center_m"][2:]
                      if e is not None])
        return {"registered": report["registered"], "mean_centre_error_cm": float(c.mean() * 100) if len(c) else None}

    plain = render_scene(SceneConfig(n_images=12, focal_jitter=0.0, distance=DISTANCE))
    lensed = render_scene(SceneConfig(n_images=12, focal_jitter=0.0, distortion=LENS, distance=DISTANCE))
    to_target = np.eye(4)
    to_target[:3, :3] *= MM
    to_target[:3, 3] = -TARGET_AT
    P_cal = [c.P @ to_target for c in cals]  # in the scene's frame and metres
    maps = [undistortion_maps(c.K, c.distortion, (640, 480)) for c in cals]
    undistorted = [undistort_image(im, cals[min(i, 1)].K, cals[min(i, 1)].distortion, maps[min(i, 1)])
                   for i, im in enumerate(lensed.images)]
    return {"no lens": errors(plain, plain.images, list(plain.P[:2])),
            "lens, calibrated distortion": errors(lensed, undistorted, P_cal),
            "lens, distortion ignored": errors(lensed, lensed.images, P_cal)}


def render_seconds(folder: Path) -> dict:
    """Rendering through a lens against without one (best of three, in-process, after a first
    call that loads the kernels): the scene's two views and one view of the target."""
    def best(make) -> float:
        make()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            make()
            times.append(time.perf_counter() - start)
        return round(min(times), 3)

    texture = load_rendered_target(folder / "target.json")
    K = np.array([[800.0, 0.0, 321.0], [0.0, 800.0, 238.5], [0.0, 0.0, 1.0]])
    R, t = _lens_views(K, np.zeros(3), 1)[0]
    out = {}
    for label, distortion in (("pinhole", ()), ("lens", LENS)):
        out[f"scene_2_views/{label}"] = best(lambda: render_scene(SceneConfig(n_images=2, textured=False,
                                                                              distortion=distortion)))
        out[f"target_view/{label}"] = best(lambda: render_target(texture, K, R, t, distortion=distortion,
                                                                 supersample=3))
    return out


def run() -> dict:
    scene = render_scene(SceneConfig(n_images=2, focal_jitter=0.0, distance=DISTANCE))
    out = {}
    with tempfile.TemporaryDirectory() as folder:
        make_target(folder, "A3", 3)
        for noise in (0.0, 2.0):
            out[f"calibration/sigma{noise:g}"], cals = calibration(noise, scene, Path(folder))
            if noise == 0.0:
                out["ring12"] = ring(cals)
        out["render_seconds"] = render_seconds(Path(folder))
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))
