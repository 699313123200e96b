"""Benchmark `big_walk` (``python benchmarks/run.py --only big_walk``; not in `make bench`'s list
while it cannot finish within its bounds, docs/dense.md): 40 photos of 6000 x 4000 (24 megapixels) walked around the
rendered box, reconstructed with the dense cloud by the command a user runs, in a child process:
its time and the peak memory of it and its pair workers together (issue #50: within 8 GB), the
cameras against the rendered ones, the cloud against the true surface.

The photos are rendered once (JPEG, quality 95, about 4 MB each) into the bench cache
(``$STEREOSEED_BENCH_CACHE``, default ``bench_output/cache``) and reused.

    python benchmarks/bench_big_walk.py        # prints the JSON
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench_dense_real import cache_dir, sampled_run
from stereoseed.experiments.evaluation import camera_errors, surface_distance
from stereoseed.geometry.projection import camera_center, compose_projection
from stereoseed.io.files import write_image, write_json
from stereoseed.io.ply import read_ply
from stereoseed.synthetic.scene import SceneConfig, _cameras, render_views

N_IMAGES = 40
SIZE = (6000, 4000)
STEP_DEG = 9.0  # 40 views once around the box
FACTOR = SIZE[0] / 640  # the ring's 640 x 480 views, 9.4 times the pixels across (a 3:2 frame)
VERSION = 1  # bump when the rendering changes (the cache is rendered again)


def scene_config() -> SceneConfig:
    base = SceneConfig(n_images=N_IMAGES, step_deg=STEP_DEG, noise_sigma=1.0, supersample=1)
    return replace(base.scaled(FACTOR), width=SIZE[0], height=SIZE[1])


def rendered(folder: Path) -> list[np.ndarray]:
    """The walk's photos in ``folder`` (rendered there one at a time the first time, with
    calib.json for the calibrated pair) and its true cameras (P per image)."""
    cfg = scene_config()
    Ks, Rs, ts = _cameras(cfg)
    Ps = [compose_projection(K, R, t) for K, R, t in zip(Ks, Rs, ts)]
    done = folder / f"rendered_v{VERSION}"
    if not done.exists():
        folder.mkdir(parents=True, exist_ok=True)
        for i, (K, R, t) in enumerate(zip(Ks, Rs, ts)):
            write_image(folder / f"img_{i:03d}.jpg", render_views(cfg, [K], [R], [t])[0])
        write_json(folder / "calib.json", {"cameras": [{"P": P.tolist()} for P in Ps[:2]], "unit": "m"})
        done.write_text("")
    return Ps


def run() -> dict:
    folder = cache_dir() / f"big_walk_{SIZE[0]}x{SIZE[1]}"
    truth = rendered(folder)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = os.environ.get("STEREOSEED_BIG_WALK_OUT", tmp)  # where to keep the result to look at
        out = sampled_run([str(Path(sys.executable).parent / "stereoseed"), "reconstruct", str(folder), "--calib",
                           str(folder / "calib.json"), "--dense", "--out", tmp, "--quiet"])
        if out["exit"] != 0:
            return out
        report = json.loads((Path(tmp) / "report.json").read_text())
        cams = json.loads((Path(tmp) / "cameras.json").read_text())
        by_name = {c["name"]: c for c in cams["images"]}
        errors, off = [], []
        for i, P in enumerate(truth[2:], start=2):
            cam = by_name.get(f"img_{i:03d}.jpg")
            if cam is not None and cam.get("P") is not None:
                errors.append(float(np.linalg.norm(camera_center(np.array(cam["P"])) - camera_center(P))))
                if errors[-1] > 0.01 * float(np.linalg.norm(camera_center(P))):  # beyond 1 % of its distance
                    off.append({"image": cam["name"], "error_mm": errors[-1] * 1000, "reliable": cam.get("reliable")})
        points, _ = read_ply(Path(tmp) / "dense.ply")
        d = surface_distance(points)
        dense = report.get("dense", {})
        out.update(images=N_IMAGES, size=list(SIZE), registered=report.get("registered"),
                   flagged=sum(1 for c in cams["images"] if c.get("registered") and c.get("reliable") is False),
                   camera_centre_error_mm_median=float(np.median(errors) * 1000),
                   camera_centre_error_mm_max=float(np.max(errors) * 1000), beyond_1pct=off,
                   dense_points=int(len(points)),
                   dense_resolution_scale=dense.get("resolution_scale"),
                   resolution_lowered=dense.get("resolution_lowered"),
                   surface_distance_mm_median=float(np.median(d) * 1000),
                   surface_distance_mm_p90=float(np.percentile(d, 90) * 1000))
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
