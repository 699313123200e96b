"""Whole-sequence quasi-dense figures: 18-image ring, fused points, accuracy against the true
surface, time on the machine's cores, peak memory."""
from __future__ import annotations

import json
import resource
import time

import numpy as np

from stereoseed.config import Config
from stereoseed.dense.densify import densify
from stereoseed.experiments.evaluation import TrueCorrespondences, camera_errors, surface_distance
from stereoseed.pipeline import reconstruct
from stereoseed.synthetic.scene import SceneConfig, render_scene


def _peak_rss_mb() -> dict:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {"self_mb": own, "largest_worker_mb": children}


def run() -> dict:
    scene = render_scene(SceneConfig(n_images=18))
    cfg = Config()
    out = {}
    for label, source in (("harris", None), ("exact-matches", TrueCorrespondences(scene))):
        recon, report = reconstruct(scene.images, scene.names, scene.P[:2], cfg, source=source)
        centre = [e for e in camera_errors([v.P_input for v in recon.views], scene.P)["center_m"][2:] if e is not None]
        densify(recon, cfg)  # warm-up: JIT caches and worker start-up
        t = time.perf_counter()
        cloud, dense = densify(recon, cfg)
        seconds = time.perf_counter() - t
        d = surface_distance(cloud.points)
        out[label] = {
            "registered": report["registered"], "camera_center_error_cm_mean": float(np.mean(centre) * 100),
            "points_before_fusion": dense["points_before_fusion"], "fused_points": dense["points"],
            "median_surface_distance_mm": float(np.median(d) * 1000),
            "p90_surface_distance_mm": float(np.percentile(d, 90) * 1000),
            "seconds": seconds, "workers": cfg.dense.workers,
            "matches_per_pair": [p["matches"] for p in dense["pairs"]],
        }
    out["peak_rss"] = _peak_rss_mb()
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
