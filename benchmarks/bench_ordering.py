"""`make bench` section `ordering` (issue #49, "photos in any order"): is every real set, its
photos shuffled, put back in walk order, and does it give the walk order's cameras?

Each walk of :data:`bench_real.SETS` is shuffled (the calibrated pair kept first; seeds 0-5),
ordered by :func:`stereoseed.matching.ordering.walk_order` from 640 px thumbnails, and
compared with the walk: ``in_walk_order`` counts the shuffles put back exactly, ``same_spot``
those that differ only by photos of one published camera (taken twice from one spot: either may
come first). The walk order itself must be kept as given. Two shuffles are then reconstructed
(default Config) and compared image by image with the walk order's run: registered, unflagged,
each camera's error against the published camera (``largest_change_pct``, of the distance).

    python benchmarks/bench_ordering.py [SET ...]   # prints the JSON
"""
from __future__ import annotations

import argparse
import json
import random
import time

import numpy as np

from bench_real import SETS, Walk, walk_images, reconstruct_listed, set_figures
from stereoseed.geometry.projection import camera_center
from stereoseed.io.files import read_image, read_middlebury_par
from stereoseed.io.sample_data import find_sample
from stereoseed.matching.ordering import thumbnail, walk_order

SEEDS = range(6)
RECONSTRUCTED = (1, 2)  # the shuffles also reconstructed


def _figures(seq, walk: Walk, names: list[str], truth: dict) -> dict:
    recon, report, seconds = reconstruct_listed([seq / n for n in names], seq / walk.par)
    fig = set_figures(recon, report, truth, seconds)
    return {"registered": fig["registered"], "unflagged": fig["unflagged"],
            "per_image": {e["image"]: (e.get("centre_error_pct"), "flag" in e) for e in fig["per_image"]}}


def run_walk(walk: Walk) -> dict:
    seq = find_sample(walk.folder)
    names = walk_images(seq, walk)
    n = len(names)
    truth = read_middlebury_par(seq / walk.par)
    centres = {k: camera_center(P) for k, P in truth.items()}
    thumbs = [thumbnail(read_image(seq / name), 640) for name in names]

    def same_spot(a: str, b: str) -> bool:
        return a == b or float(np.linalg.norm(centres[a] - centres[b])) < 1e-9

    kept, why, _ = walk_order(thumbs)
    shuffles, seconds = {}, []
    for seed in SEEDS:
        perm = [0, 1] + random.Random(seed).sample(range(2, n), n - 2)
        t = time.perf_counter()
        order, _, _ = walk_order([thumbs[i] for i in perm])
        seconds.append(time.perf_counter() - t)
        shuffles[seed] = [names[perm[i]] for i in order]
    exact = sum(got == names for got in shuffles.values())
    spot = sum(got != names and all(same_spot(a, b) for a, b in zip(got, names)) for got in shuffles.values())
    walk_run = _figures(seq, walk, names, truth)
    runs = {}
    for seed in RECONSTRUCTED:
        got = _figures(seq, walk, shuffles[seed], truth)
        change = [abs(got["per_image"][k][0] - e[0]) for k, e in walk_run["per_image"].items()
                  if e[0] is not None and got["per_image"].get(k, (None,))[0] is not None]
        runs[seed] = {"registered": got["registered"], "unflagged": got["unflagged"].get("count"),
                      "unflagged_median_pct": got["unflagged"].get("median_pct"),
                      "unflagged_worst_pct": got["unflagged"].get("worst_pct"),
                      "flags_as_walk": all(got["per_image"].get(k, (None, None))[1] == e[1]
                                           for k, e in walk_run["per_image"].items()),
                      "largest_change_pct": round(max(change), 4) if change else None}
    return {"images": n, "walk_kept": kept == list(range(n)) and why is None,
            "in_walk_order": f"{exact}/{len(SEEDS)}", "same_spot": f"{spot}/{len(SEEDS)}",
            "ordering_seconds_median": round(float(np.median(seconds)), 2),
            "walk": {"registered": walk_run["registered"], "unflagged": walk_run["unflagged"].get("count"),
                     "unflagged_median_pct": walk_run["unflagged"].get("median_pct"),
                     "unflagged_worst_pct": walk_run["unflagged"].get("worst_pct")},
            "shuffled_runs": runs}


def run(sets: list[str] | None = None) -> dict:
    return {name: run_walk(SETS[name]) for name in (sets or SETS)}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sets", nargs="*", help=f"of {', '.join(SETS)} (default: all)")
    args = parser.parse_args()
    print(json.dumps(run(args.sets or None), indent=1, default=str))
