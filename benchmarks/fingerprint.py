"""Fingerprint of what the reconstruction computes, to check that a refactoring changes nothing.

    python benchmarks/fingerprint.py save before.npz [--real]      # on the old code
    python benchmarks/fingerprint.py compare before.npz [--real]   # on the new code: max differences

Runs both modes on the synthetic box (sigma 0 and 2), the plain box, a synthetic rig walk and,
when the data is there, templeSparseRing; with ``--real`` also every set of `make bench`'s
`real` section and every walk of its `walks` section. Keeps every camera, every live point, every
camera's flag and the whole per-image report (its timings aside).
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from stereoseed.config import Config, PipelineConfig
from stereoseed.experiments.paper import shared_data_dir
from stereoseed.synthetic.rig import RigConfig, render_rig
from stereoseed.synthetic.scene import SceneConfig, render_scene


def _runs(real: bool):
    from stereoseed.pipeline import load_sequence, reconstruct

    scenes = {"box": SceneConfig(n_images=8), "box_noisy": SceneConfig(n_images=8, noise_sigma=2.0),
              "plain": SceneConfig(n_images=8, textured=False)}
    for name, sc in scenes.items():
        scene = render_scene(sc)
        for mode in ("paper", "accurate"):
            yield f"{name}/{mode}", reconstruct(scene.images, scene.names, scene.P[:2],
                                                Config(pipeline=PipelineConfig(mode=mode)))
    rig = render_rig(RigConfig(noise_sigma=1.0, stations=5)).scene
    yield "rig/accurate", reconstruct(rig.images, rig.names, rig.P[:2], Config(), rig=True)
    data = shared_data_dir()  # $STEREOSEED_DATA, else ../shared/data
    seq = data / "templeSparseRing"
    if seq.is_dir():
        images, names, P_pair = load_sequence(str(seq / "ring_order.txt"), str(seq / "templeSR_par.txt"))
        for mode in ("paper", "accurate"):
            yield f"temple/{mode}", reconstruct(images[:10], names[:10], P_pair,
                                                Config(pipeline=PipelineConfig(mode=mode)))
    if not real:
        return
    from bench_real import SETS, walk_images
    from bench_walks import WALKS

    for name, walk in {**SETS, **WALKS}.items():
        folder = data / walk.folder
        if not folder.is_dir():
            continue
        with tempfile.TemporaryDirectory() as tmp:
            listing = Path(tmp) / "walk.txt"
            listing.write_text("".join(f"{folder / n}\n" for n in walk_images(folder, walk)))
            images, names, P_pair = load_sequence(str(listing), str(folder / walk.par))
        yield f"real {name}", reconstruct(images, names, P_pair, Config())


def _without_timings(value):
    """A report with its timings left out (they differ from run to run), as JSON text."""
    if isinstance(value, dict):
        return {k: _without_timings(v) for k, v in value.items() if k not in ("seconds", "time_s")}
    if isinstance(value, list):
        return [_without_timings(v) for v in value]
    return value


def fingerprint(real: bool = False) -> dict[str, np.ndarray]:
    out = {}
    for key, (recon, report) in _runs(real):
        Ps = np.stack([v.P_input if v.P_input is not None else np.full((3, 4), np.nan) for v in recon.views])
        pts, _ = recon.live_points()
        out[f"{key}/P"] = Ps / np.linalg.norm(Ps[:, 2, :3], axis=1)[:, None, None]
        out[f"{key}/points"] = pts
        flags = [[v.name, v.reliable, v.flag_reason] for v in recon.views]
        out[f"{key}/flags"] = np.array(json.dumps(flags))
        out[f"{key}/per_image"] = np.array(json.dumps(_without_timings(report["per_image"]), default=str))
        print(key, report["registered"], "registered,", len(pts), "points", file=sys.stderr)
    return out


def compare(before: dict[str, np.ndarray], after: dict[str, np.ndarray]) -> bool:
    same = True
    for key in before:
        a, b = before[key], after.get(key)
        if b is None:
            print(f"{key}: missing")
            same = False
        elif a.dtype.kind in "UO":
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
            same &= nan_same and d == 0.0
    return same


if __name__ == "__main__":
    what, path = sys.argv[1], sys.argv[2]
    fp = fingerprint(real="--real" in sys.argv[3:])
    if what == "save":
        np.savez(path, **fp)
    else:
        sys.exit(0 if compare(dict(np.load(path)), fp) else 1)
