"""Fingerprint of what the reconstruction computes, to check that a refactoring changes nothing.

    python benchmarks/fingerprint.py save before.npz      # on the old code
    python benchmarks/fingerprint.py compare before.npz   # on the new code: max differences

Runs both modes on the synthetic box (sigma 0 and 2), the plain box and, when the data is there,
templeSparseRing, and keeps every camera, every live point and the per-image report counts.
"""
from __future__ import annotations

import json
import sys

import numpy as np

from stereoseed.config import Config, PipelineConfig
from stereoseed.experiments.paper import shared_data_dir
from stereoseed.synthetic.scene import SceneConfig, render_scene

COUNTS = ("status", "matches", "chained_points", "resection_inliers", "resection_model", "new_points",
          "tracked_observations", "removed_observations", "motion_prior_correspondences", "three_view_points")


def _runs():
    from stereoseed.pipeline import load_sequence, reconstruct

    scenes = {"box": SceneConfig(n_images=8), "box_noisy": SceneConfig(n_images=8, noise_sigma=2.0),
              "plain": SceneConfig(n_images=8, textured=False)}
    for name, sc in scenes.items():
        scene = render_scene(sc)
        for mode in ("paper", "accurate"):
            yield f"{name}/{mode}", reconstruct(scene.images, scene.names, scene.P[:2],
                                                Config(pipeline=PipelineConfig(mode=mode)))
    data = shared_data_dir()  # $STEREOSEED_DATA, else ../shared/data
    seq = data / "templeSparseRing"
    if seq.is_dir():
        images, names, P_pair = load_sequence(str(seq / "ring_order.txt"), str(seq / "templeSR_par.txt"))
        for mode in ("paper", "accurate"):
            yield f"temple/{mode}", reconstruct(images[:10], names[:10], P_pair,
                                                Config(pipeline=PipelineConfig(mode=mode)))


def fingerprint() -> dict[str, np.ndarray]:
    out = {}
    for key, (recon, report) in _runs():
        Ps = np.stack([v.P_input if v.P_input is not None else np.full((3, 4), np.nan) for v in recon.views])
        pts, _ = recon.live_points()
        out[f"{key}/P"] = Ps / np.linalg.norm(Ps[:, 2, :3], axis=1)[:, None, None]
        out[f"{key}/points"] = pts
        counts = [{c: r.get(c) for c in COUNTS} for r in report["per_image"]]
        out[f"{key}/counts"] = np.array(json.dumps(counts))
        print(key, report["registered"], "registered,", len(pts), "points", file=sys.stderr)
    return out


def compare(before: dict[str, np.ndarray], after: dict[str, np.ndarray]) -> bool:
    same = True
    for key in before:
        a, b = before[key], after.get(key)
        if b is None:
            print(f"{key}: missing")
            same = False
        elif key.endswith("/counts"):
            if str(a) != str(b):
                print(f"{key}: differ\n  before {a}\n  after  {b}")
                same = False
        elif a.shape != b.shape:
            print(f"{key}: shape {a.shape} -> {b.shape}")
            same = False
        else:
            d = float(np.nanmax(np.abs(a - b))) if a.size else 0.0
            nan_same = np.array_equal(np.isnan(a), np.isnan(b))
            print(f"{key}: max |diff| {d:.3g}" + ("" if nan_same else " (registration differs)"))
            same &= nan_same and d < 1e-6
    return same


if __name__ == "__main__":
    what, path = sys.argv[1], sys.argv[2]
    fp = fingerprint()
    if what == "save":
        np.savez(path, **fp)
    else:
        sys.exit(0 if compare(dict(np.load(path)), fp) else 1)
