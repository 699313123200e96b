"""`make bench` section `rig`: a stereo rig walked with both cameras (issue #38) against the
paper's single moving camera over the same second-camera images, on the project's renderer.

Per scene: every image registered or not, the mean camera-centre error of the right camera's
images after the first station (the images both runs place), each station's relative pose against
the calibrated rig, the scale over the walk (the first and last stations' distance against the
truth) and the time per station against the time per single-camera insertion (whole runs, after
a warm-up, the fastest of three each; for the textured walk also the whole `stereoseed
reconstruct` command a user waits for, images read and results written). The calibrated pair is the true first station, as the other synthetic benchmarks take
the true pair.

    python benchmarks/bench_rig.py      # prints the JSON
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from bench_speed import BIN, timed_process
from stereoseed.config import Config
from stereoseed.io.files import write_json
from stereoseed.estimators.rig_resection import Rig
from stereoseed.geometry.projection import camera_center
from stereoseed.pipeline import reconstruct
from stereoseed.synthetic.rig import RigConfig, render_rig

SCENES = {
    "textured_30deg": RigConfig(noise_sigma=1.0),
    "plain_box_30deg": RigConfig(noise_sigma=1.0, textured=False),
    "textured_45deg": RigConfig(noise_sigma=1.0, step_deg=45.0, stations=8),
}


def _errors(recon, truth) -> list[float | None]:
    return [float(np.linalg.norm(camera_center(v.P_input) - camera_center(P))) if v.registered else None
            for v, P in zip(recon.views, truth)]


def _relative_pose_error(recon, rig) -> float:
    """The largest difference over the stations between the right camera's pose relative to the
    left and the calibrated rig's (rotation matrix entries and translation, the model's unit)."""
    worst = 0.0
    for s in range(len(recon.views) // 2):
        left, right = recon.views[2 * s], recon.views[2 * s + 1]
        if not (left.registered and right.registered):
            continue
        station = Rig.from_projections(left.P, right.P)
        worst = max(worst, float(np.abs(station.R_rl - rig.R_rl).max()), float(np.abs(station.t_rl - rig.t_rl).max()))
    return worst


def _timed(runs: int, *args, **kwargs) -> tuple[tuple, float]:
    """(the reconstruction, its fastest time of ``runs``): on a shared machine one run's time
    moves by 10-20 %, so a ratio of two single runs moved from 1.6 to 2.0."""
    best = np.inf
    for _ in range(runs):
        t = time.perf_counter()
        out = reconstruct(*args, **kwargs)
        best = min(best, time.perf_counter() - t)
    return out, best


def _commands(scene, walk, folder: Path) -> dict[str, list[str]]:
    """The two walks written as a user's folders (the rig's left/ and right/, the single camera's
    pair and walk in name order, each a calib.json of its pair): the command each runs."""
    s = scene.scene
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
    for image, name in zip(s.images, s.names):
        cv2.imwrite(str(folder / name.split("_")[0] / name), image)
    (folder / "single").mkdir()
    for k, image in enumerate(walk.images):
        cv2.imwrite(str(folder / "single" / f"{k:03d}.png"), image)
    for name, Ps in (("rig", s.P[:2]), ("single", walk.P[:2])):
        write_json(folder / f"{name}.json", {"cameras": [{"P": np.asarray(P).tolist()} for P in Ps]})
    cli = [str(BIN / "stereoseed"), "reconstruct", "--quiet"]
    return {"rig": cli + ["--rig", str(folder / "left"), str(folder / "right"), "--calib", str(folder / "rig.json"),
                          "--out", str(folder / "out_rig")],
            "single": cli + [str(folder / "single"), "--calib", str(folder / "single.json"),
                             "--out", str(folder / "out_single")]}


def _whole_commands(scene, walk, runs: int) -> dict:
    """The command a user waits for, each the fastest of ``runs`` (a result set is replaced by
    the next run's)."""
    with tempfile.TemporaryDirectory() as tmp:
        commands = _commands(scene, walk, Path(tmp))
        seconds = {}
        for name, args in commands.items():
            done = [timed_process(args) for _ in range(runs)]
            if any(d["returncode"] for d in done):
                return {"failed": {name: d["stderr"] for d in done if d["returncode"]}}
            seconds[name] = min(d["seconds"] for d in done)
    # both commands pay the same start (interpreter, imports, compiled-code cache) and writing:
    # this ratio is the user's wait, nearer 1 than the per-station cost above
    return {"rig_seconds": seconds["rig"], "single_seconds": seconds["single"],
            "ratio_rig_over_single": seconds["rig"] / seconds["single"]}


def run_scene(config: RigConfig, runs: int = 3, whole_commands: bool = False) -> dict:
    scene = render_rig(config)
    s = scene.scene
    walk = scene.single_camera_walk()
    reconstruct(s.images[:4], s.names[:4], s.P[:2], Config(), rig=True)  # warm-up: compile, caches
    (recon, report), rig_s = _timed(runs, s.images, s.names, s.P[:2], Config(), rig=True)
    (single, single_report), single_s = _timed(runs, walk.images, walk.names, walk.P[:2], Config())
    rig_err, single_err = _errors(recon, s.P), _errors(single, walk.P)
    right = [e for e in rig_err[3::2]]  # the right images after the first station: the single walk's images
    both = [(a, b) for a, b in zip(right, single_err[2:]) if a is not None and b is not None]
    centres = [camera_center(recon.views[v].P_input) for v in (0, len(recon.views) - 2)]
    truth = [camera_center(s.P[v]) for v in (0, len(recon.views) - 2)]
    scale = (np.linalg.norm(centres[1] - centres[0]) / np.linalg.norm(truth[1] - truth[0]) - 1.0
             if recon.views[-2].registered else None)
    stations = config.stations - 1
    return {
        "rig": {"registered": f"{report['registered']}/{report['images']}",
                "flagged": len((report["final"].get("trust") or {}).get("flagged") or {}),
                "right_centre_error_mm_mean": 1000 * float(np.mean([a for a, _ in both])) if both else None,
                "centre_error_mm_per_image": [None if e is None else round(1000 * e, 3) for e in rig_err],
                "relative_pose_max_error": _relative_pose_error(recon, recon.rig),
                "scale_error_pct": None if scale is None else 100 * float(scale),
                "seconds": rig_s, "seconds_per_station": rig_s / stations},
        "single": {"registered": f"{single_report['registered']}/{single_report['images']}",
                   "right_centre_error_mm_mean": 1000 * float(np.mean([b for _, b in both])) if both else None,
                   "centre_error_mm_per_image": [None if e is None else round(1000 * e, 3) for e in single_err],
                   "seconds": single_s, "seconds_per_insertion": single_s / stations},
        "error_ratio_rig_over_single": (float(np.mean([a for a, _ in both]) / np.mean([b for _, b in both]))
                                        if both else None),
        "cost_ratio_station_over_insertion": rig_s / single_s,
        **({"whole_command": _whole_commands(scene, walk, runs)} if whole_commands else {}),
    }


def run() -> dict:
    # the cost figure of issue #38 is the textured walk's, also timed as the whole command
    return {name: run_scene(config, whole_commands=name == "textured_30deg") for name, config in SCENES.items()}


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))
