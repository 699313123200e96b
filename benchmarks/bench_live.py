"""`make bench` section `live`: a simulated capture of templeSparseRing for `stereoseed live`: its
photos put into a watched folder one at a time at a fixed rate (in ring_order.txt's order, each
written beside and renamed in, as a sync tool does), the page followed by a client of its event
stream. Per photo: the latency from the file's arrival to the first pushed state that shows it
(median, p95), and the process's memory (peak and after each photo).

    python benchmarks/bench_live.py [SECONDS_BETWEEN_PHOTOS]
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


def run(rate_s: float = RATE_S) -> dict:
    folder = find_sample(SET)
    if folder is None:
        return {"skipped": missing_message(SET)}
    photos = list_images(folder / "ring_order.txt")
    calib = folder / "templeSR_par.txt"
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

        def follow() -> None:  # a browser's event stream: what makes a state "shown"
            started.wait(60)
            try:
                with urllib.request.urlopen(urls[0] + "events", timeout=120) as stream:
                    while stream.readline():
                        pass
            except OSError:
                pass

        threads = [threading.Thread(target=f, daemon=True) for f in (feed, follow)]
        for t in threads:
            t.start()
        timings: list[dict] = []
        t0 = time.perf_counter()
        report = run_live(watch, calib, Path(tmp) / "result", live=LiveConfig(), until=len(photos), port=0,
                          on_start=lambda url: (urls.append(url), started.set()), timings=timings)
        total = time.perf_counter() - t0
    latency = [t["shown_at"] - written[t["name"]] for t in timings if t["shown_at"] is not None]
    return {"set": SET, "photos": len(photos), "seconds_between_photos": rate_s,
            "registered": report["registered"], "points": report["points"],
            "latency_s": {"median": float(np.median(latency)), "p95": float(np.percentile(latency, 95)),
                          "max": float(np.max(latency)), "shown": len(latency)},
            "finishing_s": report["timing"]["stages_s"]["finishing"], "run_s": total,
            "memory_mb": {"peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
                          "after_first_photo": rss[0] if rss else None, "after_last_photo": rss[-1] if rss else None}}


if __name__ == "__main__":
    print(json.dumps(run(*(float(a) for a in sys.argv[1:])), indent=1))
