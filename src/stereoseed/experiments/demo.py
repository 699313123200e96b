"""`stereoseed demo`: render the box scene, calibrate the pair from its pattern, reconstruct,
and report the error against the ground truth. Everything it writes goes to one folder. Its
lines go to ``say`` (the CLI passes ``print``; by default they are logged)."""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from stereoseed.estimators.calibration import calibrate_camera
from stereoseed.geometry.projection import camera_center
from stereoseed.config import Config
from stereoseed.dense.densify import densify
from stereoseed.experiments.evaluation import camera_errors, reconstruct_corners, rms_3d, surface_distance
from stereoseed.io.files import write_json
from stereoseed.pipeline import reconstruct, save_outputs
from stereoseed.output.result_set import ResultSet
from stereoseed.synthetic.scene import SceneConfig, render_scene, write_scene

log = logging.getLogger(__name__)


def run_demo(out: Path, n_images: int = 14, noise: float = 0.0, dense: bool = True,
             say: Callable[[str], None] = log.info, cfg: Config | None = None) -> int:
    """Render the box scene, calibrate its pair, reconstruct it into ``out`` and ``say`` the
    errors against the ground truth (cfg: the run's settings, default ``Config()``)."""
    with ResultSet(out) as results:  # one run per result folder: a second one is refused at once
        results.check()
        staging = results.open()
        try:
            code = _run(staging, out, n_images, noise, dense, say, cfg or Config())
            results.commit()
        except BaseException:
            results.abandon()
            raise
    return code


def _run(staging: Path, out: Path, n_images: int, noise: float, dense: bool, say: Callable[[str], None],
         cfg: Config) -> int:
    """The demo, writing into ``staging``, which becomes ``out`` when it is done."""
    t0 = time.perf_counter()
    scene = render_scene(SceneConfig(n_images=n_images, noise_sigma=noise))
    write_scene(scene, staging / "scene")
    say(f"rendered {n_images} images of the 34x34x44 cm box ({time.perf_counter() - t0:.1f} s) -> {out / 'scene'}")

    pattern, pts1, pts2 = scene.calibration_points()
    cams = [calibrate_camera(pattern, pts, what=f"pair image {i + 1}") for i, pts in enumerate((pts1, pts2))]
    write_json(staging / "calib.json", {"cameras": [c.to_dict() for c in cams], "unit": "m"})  # the scene's
    for i, c in enumerate(cams):
        err = np.linalg.norm(camera_center(c.P) - camera_center(scene.P[i]))
        say(f"calibrated camera {i + 1} from {c.n_points} pattern corners: reprojection RMS {c.rms_px:.3f} px, "
              f"centre error {err * 1000:.2f} mm")

    t_run = time.perf_counter()
    recon, report = reconstruct(scene.images, scene.names, [c.P for c in cams], cfg)
    stages = {"sparse": time.perf_counter() - t_run}
    errors = camera_errors([v.P_input for v in recon.views], scene.P)
    corners, seen = reconstruct_corners([v.P for v in recon.views], [v.features for v in recon.views],
                                        scene.corners, scene.P,
                                        [scene.corner_visibility(i) for i in range(scene.n_images)])
    corner_rms = rms_3d(corners, scene.corners[seen]) if len(seen) else float("nan")
    report["ground_truth"] = {"camera_center_error_m": errors["center_m"], "rotation_error_deg": errors["rotation_deg"],
                              "corners_reconstructed": int(len(seen)), "corners_rms_3d_m": corner_rms}
    if dense:
        cloud, report["dense"] = densify(recon, cfg, staging)
        stages["dense"] = time.perf_counter() - t_run - stages["sparse"]
        distance = surface_distance(cloud.points)
        report["dense"]["median_surface_distance_m"] = float(np.median(distance)) if len(distance) else None
    report.update(unit="m", timing={"total_s": sum(stages.values()), "stages_s": stages})
    save_outputs(recon, report, staging, cfg, dense=cloud if dense else None)
    centre = [e for e in errors["center_m"][2:] if e is not None]
    say(f"registered {report['registered']}/{report['images']} images, {report['points']} sparse points, "
          f"reprojection RMS {report['reprojection']['rms_px']:.3f} px")
    if centre:
        say(f"camera centre error (moving camera): mean {np.mean(centre) * 100:.3f} cm, max {np.max(centre) * 100:.3f} cm")
    say(f"3D RMS of the {len(seen)} reconstructed box corners (eq. 13, no alignment): {corner_rms * 100:.3f} cm")
    if dense:
        d = report["dense"]
        say(f"quasi-dense: {d['points']} fused points from {len(d['pairs'])} pairs in {d['seconds']:.1f} s, "
              f"median distance to the true surface {d['median_surface_distance_m'] * 1000:.2f} mm")
    say(f"total {time.perf_counter() - t0:.1f} s; outputs in {out}")
    return 0
