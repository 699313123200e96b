"""`make bench` section `stability` (issue #47, part 1): does a camera move, between copies of
the same photos that differ only in how they were saved, by more than the uncertainty the run
states for it? This needs no ground truth: it is the check a user can make on their own data.

Each walk of :data:`bench_real.SETS` is reconstructed (default Config) from its images as
published and from copies written to a temporary folder under the same file names (the par file
names the images; the decoder reads a file by its content, so a JPEG named ``x.png`` is read as
the JPEG it is), the calibration file unchanged:

* ``png``: the decoded pixels, lossless: the pixels the run reads from the original, PNG or
  JPEG, so its run is the original's (a check that nothing else differs between runs);
* ``jpeg90``, ``jpeg97``: the decoded pixels encoded as JPEG at quality 90 and 97;
* ``noise1``: the decoded pixels plus a uniform integer in {-1, 0, 1} per pixel (seeded, the
  same in the three channels, so the grey image moves by one grey level), clipped, as PNG.

Per camera after the pair and per copy: its centre, whether placed and flagged, its stated
1-sigma (the largest of ``uncertainty.position_sigma``'s three axes) and its error against the
published camera (:func:`bench_real.set_figures`). Across the copies where it is placed: the
spread (each copy's distance from the per-axis median of its distinct centres, the largest of
them) and that distance over the copy's sigma (``moved_sigma``; the camera's ``spread_sigma``:
the largest over the copies). What issue #47 requires: a camera that moves by
more than 3 sigma in a copy is flagged in that copy; the ones that are not are named
``unstable_unflagged``.

    python benchmarks/bench_stability.py [SET ...] [--copies png,jpeg90,...]   # prints the JSON
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np

from bench_real import SETS, Walk, walk_images, reconstruct_listed, set_figures
from stereoseed.config import Config
from stereoseed.geometry.projection import camera_center
from stereoseed.io.files import read_image, read_middlebury_par
from stereoseed.io.sample_data import find_sample, missing_message

NOISE_SEED = 47
# a camera is stable when it moves by at most this many of its stated sigmas (issue #47)
K_SIGMA = 3.0
# and no camera it vouches for may be more than this % of the scene's distance off the truth
MAX_ERROR_PCT = 1.0


def _jpeg(quality: int):
    return lambda image, i: cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])[1]


def _noisy_png(image: np.ndarray, i: int) -> np.ndarray:
    # one draw per pixel, added to B, G and R alike: the grey image the run works on moves by
    # exactly one grey level where the draw is not 0 (independent draws would mostly cancel)
    noise = np.random.default_rng([NOISE_SEED, i]).integers(-1, 2, image.shape[:2])[..., None]
    return cv2.imencode(".png", np.clip(image.astype(np.int16) + noise, 0, 255).astype(np.uint8))[1]


# name -> (decoded uint8 BGR image, its index in the walk) -> the encoded file's bytes
COPIES = {
    "png": lambda image, i: cv2.imencode(".png", image)[1],
    "jpeg90": _jpeg(90),
    "jpeg97": _jpeg(97),
    "noise1": _noisy_png,
}


def write_copy(paths: list[Path], folder: Path, encode) -> list[Path]:
    """The images ``paths`` decoded as the run decodes them and written again by ``encode``
    into ``folder`` under their own file names (what the par file looks the pair up by)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, path in enumerate(paths):
        out.append(folder / path.name)
        out[-1].write_bytes(np.asarray(encode(read_image(path), i)).tobytes())
    return out


def run_walk(walk: Walk, copies: list[str] | None = None, count: int | None = None, cfg: Config = Config()) -> dict:
    """One walk (its first ``count`` images when given) from its images and from each copy
    (:data:`COPIES`' names): the figures per copy and per camera, the walk's summary."""
    seq = find_sample(walk.folder)  # $STEREOSEED_DATA, else ../shared/data, else what data fetch wrote
    if seq is None:
        return {"skipped": missing_message(walk.folder)}
    paths = [seq / n for n in walk_images(seq, walk)[:count]]
    truth = read_middlebury_par(seq / walk.par)
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for copy in ["original"] + list(COPIES if copies is None else copies):
            listed = paths if copy == "original" else write_copy(paths, Path(tmp) / copy, COPIES[copy])
            recon, report, seconds = reconstruct_listed(listed, seq / walk.par, cfg)
            runs[copy] = _copy_figures(recon, report, truth, seconds)
    return compare_copies(runs)


def _copy_figures(recon, report: dict, truth: dict, seconds: float) -> dict:
    """One run's figures: bench_real's, and per camera its centre and stated sigma."""
    figures = set_figures(recon, report, truth, seconds)
    for v, entry in zip(recon.views, figures["per_image"]):
        if v.registered and v.P_input is not None:
            entry["centre"] = camera_center(v.P_input)
            u = v.uncertainty
            # the largest axis: a camera's spread is a distance, in no particular direction
            entry["sigma"] = None if u is None else float(np.max(u.position_sigma))
            if u is not None and not u.determined:
                entry["sigma_reason"] = u.reason
    return figures


def _ratio(distance: float, sigma: float | None) -> float:
    """distance over sigma: an undetermined camera (infinite sigma) vouches for no position (0);
    one stating no sigma at all is taken at its word of none (inf, unless it did not move)."""
    if sigma is None or sigma == 0:
        return 0.0 if distance == 0 else float("inf")
    return distance / sigma


def compare_copies(runs: dict[str, dict]) -> dict:
    """The per-camera spread across the copies (``runs``: :func:`_copy_figures` by copy name)
    and the walk's summary (:func:`summarise`)."""
    first = next(iter(runs.values()))
    cameras = []
    for k, entry in enumerate(first["per_image"][2:], start=2):
        name = entry["image"]
        per_copy = {copy: r["per_image"][k] for copy, r in runs.items()}
        placed = {c: e for c, e in per_copy.items() if "centre" in e}
        camera = {"image": name, "copies": {}}
        if placed:
            # a centre met twice is one run met twice (the PNG of decoded pixels gives the original's
            # run to the bit): counted once, or it would pull the median onto itself
            median = np.median(np.unique([e["centre"] for e in placed.values()], axis=0), axis=0)
            for c, e in placed.items():
                moved = float(np.linalg.norm(e["centre"] - median))
                camera["copies"][c] = {"moved": moved, "moved_sigma": _ratio(moved, e["sigma"]), "sigma": e["sigma"],
                                       "error": e["centre_error"], "error_pct": e["centre_error_pct"], "flag": e.get("flag"),
                                       # the published cameras' own error as this copy's run measures it
                                       "allowance": runs[c]["coverage"]["allowance"]}
            camera["spread"] = max(v["moved"] for v in camera["copies"].values())
            camera["spread_sigma"] = max(v["moved_sigma"] for v in camera["copies"].values())
            camera["max_sigma"] = max((e["sigma"] for e in placed.values() if e["sigma"] is not None), default=None)
        for c, e in per_copy.items():
            if c not in placed:
                camera["copies"][c] = {"status": e["status"], "reason": e.get("reason")}
        cameras.append(camera)
    distance = first["distance"]
    return {"images": first["images"], "distance": distance, "summary": summarise(cameras, list(runs), first["images"]),
            "per_copy": {c: {"registered": r["registered"], "seconds": r["seconds"], "distance": r["distance"],
                             "unflagged": r["unflagged"], "from_original": _from_original(r, first)}
                         for c, r in runs.items()},
            "cameras": cameras}


def _from_original(run: dict, original: dict) -> float | None:
    """The farthest a camera placed in both runs lies from its place in ``original``: 0 says the
    copy's pixels (a PNG of a PNG's, or of a JPEG's decoded pixels) gave the run nothing new."""
    moved = [float(np.linalg.norm(a["centre"] - b["centre"])) for a, b in zip(run["per_image"], original["per_image"])
             if "centre" in a and "centre" in b]
    return max(moved, default=None)


def summarise(cameras: list[dict], copies: list[str], images: int) -> dict:
    """What issue #47 asks of a walk, from :func:`compare_copies`' cameras."""
    def unflagged_in(cam, c):
        e = cam["copies"][c]
        return "moved" in e and e["flag"] is None

    # the cameras the run vouches for in every copy where it placed them, placed in two or more
    vouched = [cam for cam in cameras if len([c for c in copies if "moved" in cam["copies"][c]]) >= 2
               and all(unflagged_in(cam, c) for c in copies if "moved" in cam["copies"][c])]
    ratios = np.array([cam["spread_sigma"] for cam in vouched])
    unstable = [{"image": cam["image"], "copies": {c: _short(cam["copies"][c]) for c in copies
                                                   if unflagged_in(cam, c) and cam["copies"][c]["moved_sigma"] > K_SIGMA}}
                for cam in cameras]
    off = [{"image": cam["image"], "copies": {c: _short(cam["copies"][c]) for c in copies
                                              if unflagged_in(cam, c) and cam["copies"][c]["error_pct"] > MAX_ERROR_PCT}}
           for cam in cameras]
    coverage, coverage_allowing = {}, {}
    for c in copies + ["all"]:
        pairs = [cam["copies"][x] for cam in cameras for x in (copies if c == "all" else [c]) if unflagged_in(cam, x)]
        covered = [e for e in pairs if _ratio(e["error"], e["sigma"]) <= K_SIGMA]
        coverage[c] = round(len(covered) / len(pairs), 3) if pairs else None
        allowed = [e for e in pairs if e["sigma"] is not None and e["error"] <= K_SIGMA * np.hypot(e["sigma"], e["allowance"])]
        coverage_allowing[c] = round(len(allowed) / len(pairs), 3) if pairs else None
    placed_unflagged = {c: sum(unflagged_in(cam, c) for cam in cameras) for c in copies}
    return {
        "vouched_in_every_copy": len(vouched),
        "stable_fraction": round(float(np.mean(ratios <= K_SIGMA)), 3) if len(ratios) else None,
        "spread_sigma_median": float(np.median(ratios)) if len(ratios) else None,
        "spread_sigma_worst": float(ratios.max()) if len(ratios) else None,
        "unstable_unflagged": [u for u in unstable if u["copies"]],
        "off_unflagged": [o for o in off if o["copies"]],
        "coverage": coverage,
        # with the published cameras' own error allowed for (bench_real.published_consistency)
        "coverage_allowing": coverage_allowing,
        # the pair counts as placed and unflagged: the share of the walk's images a user gets
        "placed_unflagged": {c: f"{n + 2}/{images}" for c, n in placed_unflagged.items()},
        "placed_unflagged_fraction": {c: round((n + 2) / images, 3) for c, n in placed_unflagged.items()},
    }


def _short(e: dict) -> dict:
    """A camera in one copy, as a summary names it."""
    return {"moved_sigma": round(e["moved_sigma"], 2), "moved": round(e["moved"], 5), "sigma": e["sigma"],
            "error_pct": e["error_pct"]}


def run(sets: list[str] | None = None, copies: list[str] | None = None) -> dict:
    return {name: run_walk(SETS[name], copies) for name in (sets or SETS)}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sets", nargs="*", help=f"of {', '.join(SETS)} (default: all)")
    parser.add_argument("--copies", default=",".join(COPIES), help="comma-separated, of " + ", ".join(COPIES))
    args = parser.parse_args()
    print(json.dumps(run(args.sets or None, args.copies.split(",")), indent=1, default=str))
