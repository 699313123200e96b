"""`make bench` section `live`: a simulated capture of templeSparseRing for `stereoseed live`: its
photos put into a watched folder one at a time at a fixed rate (in ring_order.txt's order, each
written beside and renamed in, as a sync tool does), the page followed by a client of its event
stream. Per photo: the latency from the file's arrival to the first pushed state that shows it
(median, p95), and the process's memory (peak and after each photo). With ``--dense`` (the
issue's setting: the dense stage's propagation running behind the walk in a worker process),
as the captures of ``run`` do; without, the sparse run alone. Then ``walk``: a 300-photo
synthetic ring (320 x 240, 1.2 degrees apart) taken by a live run as fast as it inserts them,
the page's state built after each as the page would: the memory along the walk and the
insertion's time.

    python benchmarks/bench_live.py [SECONDS_BETWEEN_PHOTOS] [--dense]
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

from stereoseed.io.files import list_images
from stereoseed.io.sample_data import find_sample, missing_message
from stereoseed.live import LiveConfig, run_live

SET = "templeSparseRing"
RATE_S = 1.0  # one photo a second: a person walking around an object, photographing as they go


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def walk(n: int = 300, dense: bool = True) -> dict:
    """The long walk (module doc); ``dense``: with the dense stage's propagation behind it, its
    matches on disk (the worker's memory is its own process's: ``worker_peak_mb``)."""
    from stereoseed.io.files import write_image, write_json
    from stereoseed.live.session import LiveRun
    from stereoseed.live.status import page_state
    from stereoseed.live.watch import Arrival
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    scene = render_scene(SceneConfig(n_images=n, step_deg=1.2, width=320, height=240, focal_px=400.0,
                                     focal0_px=390.0, supersample=1))
    rss, seconds = {}, []
    with tempfile.TemporaryDirectory(prefix="bench-live-walk-") as tmp:
        calib = write_json(Path(tmp) / "calib.json", {"cameras": [{"P": P.tolist()} for P in scene.P[:2]]})
        paths = [write_image(Path(tmp) / name, image) for name, image in zip(scene.names, scene.images)]
        del scene
        run = LiveRun(calib, Path(tmp) / "result", dense=dense)
        mapper, state = [], []
        for i, path in enumerate(paths, 1):
            t = time.perf_counter()
            report = run.add(Arrival(path, path.name, path.read_bytes(), True, time.monotonic()))
            t1 = time.perf_counter()
            page_state(run.recon, run.names, run.unit)
            seconds.append(time.perf_counter() - t)
            state.append(time.perf_counter() - t1)
            mapper.append((report or {}).get("seconds", {}).get("total", 0.0))
            if i in (30, 60, 100, 150, 200, 250, 300) or i == n:
                rss[i] = _rss_mb()
        t = time.perf_counter()
        report = run.finish(dense)
        finishing = time.perf_counter() - t
    return {"photos": n, "registered": report["registered"], "rss_mb_after_photo": rss,
            "photo_s": {"photos_10_19": float(np.median(seconds[9:19])), "last_ten": float(np.median(seconds[-10:]))},
            # of which the mapper's insertion (its report's seconds) and the page's state
            "insertion_s": {"photos_10_19": float(np.median(mapper[9:19])), "last_ten": float(np.median(mapper[-10:]))},
            "page_state_s": {"photos_10_19": float(np.median(state[9:19])), "last_ten": float(np.median(state[-10:]))},
            "live_s": float(sum(seconds)), "finishing_s": finishing,
            "dense": {"pairs": len(report["dense"]["pairs"]), "pairs_found_before": report["dense"]["pairs_found_before"],
                      "points": report["dense"]["points"], "seconds_after_stop": report["dense"]["seconds"]}
            if dense else None,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
            "worker_peak_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e3}


def run(rate_s: float = RATE_S) -> dict:
    return {"capture": capture(rate_s, dense=True), "ring36": ring36(rate_s, dense=True),
            "video": video_ring(), "capture_sparse": capture(rate_s), "walk": walk()}


VIDEO_FPS = 12.0  # a walk filmed at 12 frames a second, 2.5 degrees a frame: a slow full turn in 12 s


def video_ring(fps: float = VIDEO_FPS, dense: bool = True) -> dict:
    """A filmed walk read at real speed (``live --video`` after the pair's two photos): the
    36-image ring's pair (640 x 480, 10 degrees apart, its true cameras as the calibration) and
    a video going on from the second camera round the whole ring, 2.5 degrees a frame, read at
    ``fps`` by the live run. Latency: from the moment the keyframe was picked from the stream to
    the first state a client was sent showing it."""
    import cv2

    from stereoseed.io.files import write_image, write_json
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    with tempfile.TemporaryDirectory(prefix="bench-live-video-") as tmp:
        pair = render_scene(SceneConfig(n_images=2, step_deg=10.0, seed=1))
        frames = render_scene(SceneConfig(n_images=144, step_deg=2.5, azimuth0_deg=40.0, focal0_px=800.0,
                                          principal_offset0_px=(0.0, 0.0), focal_jitter=0.0, pose_jitter=False,
                                          seed=1))
        photos = [write_image(Path(tmp) / f"pair{i}.png", image) for i, image in enumerate(pair.images)]
        calib = write_json(Path(tmp) / "calib.json", {"cameras": [{"P": P.tolist()} for P in pair.P[:2]]})
        video = Path(tmp) / "walk.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), fps, frames.images[0].shape[1::-1])
        for image in frames.images:
            writer.write(image)
        writer.release()
        timings: list[dict] = []
        started, urls = threading.Event(), []
        threading.Thread(target=_follow, args=(started, urls), daemon=True).start()
        t0 = time.perf_counter()
        report = run_live(None, calib, Path(tmp) / "result", live=LiveConfig(), port=0, video=video, pair=photos,
                          timings=timings, dense=dense, on_start=lambda url: (urls.append(url), started.set()))
        total = time.perf_counter() - t0
    latency = [t["shown_at"] - t["settled_at"] for t in timings[2:] if t["shown_at"] is not None]
    return {"set": f"synthetic ring filmed: the pair, then 144 frames 2.5 degrees apart at {fps:g} frames a second",
            "keyframes": len(timings) - 2, "registered": report["registered"], "images": report["images"],
            "latency_s": {"median": float(np.median(latency)), "p95": float(np.percentile(latency, 95)),
                          "max": float(np.max(latency)), "shown": len(latency)},
            "finishing_s": report["timing"]["stages_s"]["finishing"], "run_s": total,
            "dense": {"pairs": len(report["dense"]["pairs"]), "pairs_found_before": report["dense"]["pairs_found_before"]}
            if dense else None}


def ring36(rate_s: float = RATE_S, dense: bool = False) -> dict:
    """The capture of bench_speed's 36-image synthetic ring (640 x 480, 10 degrees apart, its
    true pair as the calibration)."""
    from stereoseed.io.files import write_json
    from stereoseed.synthetic.scene import SceneConfig, render_scene, write_scene

    with tempfile.TemporaryDirectory(prefix="bench-live-ring-") as tmp:
        scene = render_scene(SceneConfig(n_images=36, step_deg=10.0, seed=1))
        photos = write_scene(scene, Path(tmp) / "ring")["images"]
        calib = write_json(Path(tmp) / "calib.json", {"cameras": [{"P": P.tolist()} for P in scene.P[:2]]})
        return {"set": "synthetic ring, 36 images at 10 degrees", **_capture(photos, calib, rate_s, dense)}


def capture(rate_s: float = RATE_S, dense: bool = False) -> dict:
    folder = find_sample(SET)
    if folder is None:
        return {"skipped": missing_message(SET)}
    return {"set": SET, **_capture(list_images(folder / "ring_order.txt"), folder / "templeSR_par.txt", rate_s, dense)}


def _follow(started: threading.Event, urls: list[str]) -> None:
    """A browser's event stream: what makes a state "shown"."""
    started.wait(60)
    try:
        with urllib.request.urlopen(urls[0] + "events", timeout=300) as stream:
            while stream.readline():
                pass
    except OSError:
        pass


def _capture(photos: list[Path], calib: Path, rate_s: float, dense: bool = False) -> dict:
    written: dict[str, float] = {}
    rss: list[float] = []
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        watch = Path(tmp) / "watch"
        watch.mkdir()
        started = threading.Event()
        urls: list[str] = []

        def feed() -> None:
            started.wait(60)
            for path in photos:
                side = watch / f".{path.name}.tmp"
                shutil.copyfile(path, side)
                os.replace(side, watch / path.name)
                written[path.name] = time.monotonic()
                time.sleep(rate_s)
                rss.append(_rss_mb())

        threads = [threading.Thread(target=feed, daemon=True),
                   threading.Thread(target=_follow, args=(started, urls), daemon=True)]
        for t in threads:
            t.start()
        timings: list[dict] = []
        t0 = time.perf_counter()
        report = run_live(watch, calib, Path(tmp) / "result", live=LiveConfig(), until=len(photos), port=0,
                          on_start=lambda url: (urls.append(url), started.set()), timings=timings, dense=dense)
        total = time.perf_counter() - t0
    latency = [t["shown_at"] - written[t["name"]] for t in timings if t["shown_at"] is not None]
    return {"photos": len(photos), "seconds_between_photos": rate_s,
            "registered": report["registered"], "points": report["points"],
            "latency_s": {"median": float(np.median(latency)), "p95": float(np.percentile(latency, 95)),
                          "max": float(np.max(latency)), "shown": len(latency)},
            "finishing_s": report["timing"]["stages_s"]["finishing"], "run_s": total,
            "dense": {"pairs": len(report["dense"]["pairs"]), "pairs_found_before": report["dense"]["pairs_found_before"],
                      "seconds_after_stop": report["dense"]["seconds"], "points": report["dense"]["points"]}
            if dense else None,
            "memory_mb": {"peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
                          "after_first_photo": rss[0] if rss else None, "after_last_photo": rss[-1] if rss else None}}


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--dense"]
    print(json.dumps(capture(*(float(a) for a in args), dense="--dense" in sys.argv) if args or "--dense" in sys.argv
                     else run(), indent=1))
