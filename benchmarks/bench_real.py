"""`make bench` section `real`: every real sequence of ../shared/data with ground-truth cameras,
each image's camera-centre error against the published cameras, and what the run said of it.

The pair (the first two images of the walk) gets the published cameras, as a calibration would;
every later camera is estimated and compared. Errors are in the sets' unit (metres) and, for the
outdoor sets, in % of the scene's distance (the median depth of the sparse points seen from the
first camera): a walk of a building and a walk of a statuette are judged alike.

    python benchmarks/bench_real.py [SET ...]      # prints the JSON; SET e.g. strechaCastleP19
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from stereoseed.config import Config
from stereoseed.sfm.pair_consistency import pair_consistency
from stereoseed.geometry.projection import camera_center, depths
from stereoseed.io.files import read_middlebury_par
from stereoseed.io.sample_data import find_sample, missing_message
from stereoseed.pipeline import load_sequence, reconstruct

class Walk(NamedTuple):
    """A walk through a set: its folder, its calibration file, every ``step``-th image from the
    ``start``-th of the walking order (reversed first when ``reverse``)."""

    folder: str
    par: str
    step: int = 1
    start: int = 0
    reverse: bool = False


SETS = {
    "strechaFountainP11": Walk("strechaFountainP11", "strechaFountainP11_par.txt"),
    "strechaCastleP19": Walk("strechaCastleP19", "strechaCastleP19_par.txt"),
    "dinoRing1-24/2": Walk("dinoRing1-24", "dinoRing1-24_par.txt", 2),
    "dinoRing1-24/3": Walk("dinoRing1-24", "dinoRing1-24_par.txt", 3),
    "dinoSparseRing": Walk("dinoSparseRing", "dinoSR_par.txt"),
    "templeSparseRing": Walk("templeSparseRing", "templeSR_par.txt"),
}


def walk_images(folder: Path, walk: Walk) -> list[str]:
    """The walk's images: ring_order.txt where the set has one, else the calibration file's
    images in name order; reversed if asked, then every ``step``-th from ``start``."""
    order = folder / "ring_order.txt"
    if order.is_file():
        names = [n.strip() for n in order.read_text().splitlines() if n.strip()]
    else:
        names = sorted(read_middlebury_par(folder / walk.par))
    return (names[::-1] if walk.reverse else names)[walk.start::walk.step]


def run_set(name: str, cfg: Config = Config()) -> dict:
    """One real set (:data:`SETS`): :func:`run_walk`."""
    return run_walk(SETS[name], cfg)


def run_walk(walk: Walk, cfg: Config = Config()) -> dict:
    """One walk: per image its status, how it was placed, its flag (when the run gives one)
    and its camera-centre error; the summary over the placed images."""
    seq = find_sample(walk.folder)  # $STEREOSEED_DATA, else ../shared/data, else what data fetch wrote
    if seq is None:
        return {"skipped": missing_message(walk.folder)}
    recon, report, seconds = reconstruct_listed([seq / n for n in walk_images(seq, walk)], seq / walk.par, cfg)
    return set_figures(recon, report, read_middlebury_par(seq / walk.par), seconds)


def reconstruct_listed(paths: list[Path], par: Path, cfg: Config = Config()) -> tuple:
    """(reconstruction, report, seconds) of the images ``paths`` in that order, through a list
    file as a user would give them, the pair's cameras from ``par`` looked up by file name."""
    with tempfile.TemporaryDirectory() as tmp:
        listing = Path(tmp) / "walk.txt"
        listing.write_text("".join(f"{p}\n" for p in paths))
        images, names, P_pair = load_sequence(str(listing), str(par))
        t = time.perf_counter()
        recon, report = reconstruct(images, names, P_pair, cfg)
        return recon, report, time.perf_counter() - t


def set_figures(recon, report: dict, truth: dict, seconds: float | None = None) -> dict:
    """A reconstructed set's figures (:func:`run_set`'s): ``truth`` the published cameras by
    image name; ``seconds`` the reconstruction's time, when it was timed."""
    names = [v.name for v in recon.views]
    # the points the first camera sees: a walk that turns leaves others behind it (negative depths)
    pts = recon.points[recon.points_seen_by(0)]
    distance = float(np.median(depths(truth[names[0]], pts))) if len(pts) else float("nan")
    per_image, placed, trusted, ratios = [], [], [], []
    for v, r in zip(recon.views, report["per_image"]):
        entry = {"image": v.name, "status": r.get("status")}
        if r.get("registered_by"):
            entry["registered_by"] = str(r["registered_by"])
        if r.get("first_registration"):  # registered again between its neighbours: what placed it first
            entry["first_registration"] = {key: str(value) for key, value in r["first_registration"].items()}
        if r.get("status") == "failed":
            entry["reason"] = r.get("reason")
        reliable = getattr(v, "reliable", True)
        if not reliable:
            entry["flag"] = getattr(v, "flag_reason", "flagged")
        if v.registered and v.P_input is not None:
            err = float(np.linalg.norm(camera_center(v.P_input) - camera_center(truth[v.name])))
            entry["centre_error"] = round(err, 5)
            entry["centre_error_pct"] = round(100 * err / distance, 3)
            u = getattr(v, "uncertainty", None)
            if u is not None:  # the stated 1-sigma position (its worst axis) and the error in sigmas
                sigma = float(np.max(u.position_sigma))
                entry["position_sigma"] = round(sigma, 6)
                entry["error_over_sigma"] = round(err / sigma, 2) if sigma > 0 else None
            if len(per_image) >= 2:
                placed.append(err)
                if reliable:
                    trusted.append(err)
                    if entry.get("error_over_sigma") is not None:
                        ratios.append(entry["error_over_sigma"])
        per_image.append(entry)

    published = published_consistency(recon, truth)
    allowance = published["allowance"]
    within = [e["centre_error"] <= 3.0 * np.hypot(e["position_sigma"], allowance)
              for k, e in enumerate(per_image) if k >= 2 and "flag" not in e and e.get("position_sigma") is not None]

    def summary(errors: list[float]) -> dict:
        if not errors:
            return {"count": 0}
        e = np.array(errors)
        return {"count": int(len(e)), "median": float(np.median(e)), "worst": float(e.max()),
                "median_pct": float(100 * np.median(e) / distance), "worst_pct": float(100 * e.max() / distance)}

    return {"images": len(names), "registered": report["registered"], "distance": distance, "seconds": seconds,
            "placed": summary(placed), "unflagged": summary(trusted),
            # the unflagged cameras' error against the published cameras in stated sigmas (worst axis)
            "coverage": {"count": len(ratios), "within_3_sigma": float(np.mean(np.array(ratios) <= 3.0)) if ratios else None,
                         "median_error_over_sigma": float(np.median(ratios)) if ratios else None,
                         # the same with the published cameras' own error allowed for (published_consistency)
                         "allowance": allowance,
                         "within_3_sigma_allowing": float(np.mean(within)) if within else None},
            "published": published,
            "per_image": per_image,
            "loop_closure": (report.get("final") or {}).get("loop_closure")}


def published_consistency(recon, truth: dict) -> dict:
    """How far the published cameras themselves are from where the images put them: each
    published camera resected (its published intrinsics held) from the run's tracks as the
    *other* published cameras triangulate them (stereoseed.sfm.pair_consistency, as a run measures its pair),
    per image its centre's offset and that resection's own 1-sigma. ``allowance``: the median,
    over the published cameras, of the offset beyond that sigma (in quadrature): the ground
    truth's own error as these images see it, which no camera of ours can be checked below.
    Views turned by 180 degrees are left out (their pixels are in the turned frame)."""
    cameras = {k: np.asarray(truth[v.name], np.float64) for k, v in enumerate(recon.views)
               if v.registered and v.name in truth and not getattr(v, "rotated_180", False)}
    measured = pair_consistency(recon, cameras, Config().trust.independent_cell_px, 3.0, cameras)
    excess = [np.sqrt(max(m["offset"] ** 2 - m["sigma"] ** 2, 0.0)) for m in measured.values()]
    per_image = {name: {"offset": round(m["offset"], 6), "sigma": round(m["sigma"], 6), "pairs": m["pairs"]}
                 for name, m in measured.items()}
    return {"allowance": float(np.median(excess)) if excess else 0.0, "per_image": per_image}


def run(sets: list[str] | None = None) -> dict:
    return {name: run_set(name) for name in (sets or SETS)}


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1:] or None), indent=1, default=str))
