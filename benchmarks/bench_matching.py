"""Interest points and matching: time of detect + describe + match for one 640x480 pair, and the
accuracy of the kept matches against the synthetic box's exact correspondences (textured box at
noise 0 and 2 grey levels, the plain box), plus the real templeSparseRing ring if present.

    python benchmarks/bench_matching.py
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import cv2
import numpy as np

from stereoseed.geometry.projection import (
    decompose_projection,
    epipolar_distances,
    fundamental_from_projections,
)
from stereoseed.config import FeatureConfig, MatchingConfig
from stereoseed.features.harris import extract_features
from stereoseed.experiments.paper import shared_data_dir
from stereoseed.io.files import read_middlebury_par
from stereoseed.matching.containers import Matches
from stereoseed.matching.pair import match_pair
from stereoseed.matching.two_view import filter_epipolar
from stereoseed.matching.zncc import match_zncc
from stereoseed.synthetic.scene import SceneConfig, render_scene


def accuracy(scene, i: int, j: int, f1, f2, m: Matches) -> dict:
    x1, x2 = m.points(f1, f2)
    xt, ok = scene.true_match(i, j, x1)
    err = np.linalg.norm(xt - x2, axis=1)[ok]

    def frac(t: float) -> float | None:
        return round(float(np.mean(err < t)), 4) if len(err) else None

    return {"kept": len(m), "evaluated": int(ok.sum()), "within_1px": frac(1.0),
            "within_3px": frac(3.0),
            "median_px": round(float(np.median(err)), 3) if len(err) else None}


def best_time(fn, repeat: int = 7) -> float:
    fn()  # warm-up (caches, lazy imports)
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def scene_figures(scene, cfg: MatchingConfig) -> dict:
    feats = [extract_features(im) for im in scene.images[:3]]
    F01 = fundamental_from_projections(scene.P[0], scene.P[1])
    out = {}
    out["pair01_known_F"] = accuracy(scene, 0, 1, feats[0], feats[1],
                                     match_pair(feats[0], feats[1], cfg, F=F01).matches)
    out["pair01_robust_F"] = accuracy(scene, 0, 1, feats[0], feats[1],
                                      match_pair(feats[0], feats[1], cfg).matches)
    out["pair12_robust_F"] = accuracy(scene, 1, 2, feats[1], feats[2],
                                      match_pair(feats[1], feats[2], cfg).matches)
    # The paper's recipe for comparison: 11x11 ZNCC > 0.8, mutual best (no ratio test), then
    # the 2 px band.
    paper = filter_epipolar(match_zncc(feats[0], feats[1], dataclasses.replace(cfg, max_ratio=None)),
                            feats[0], feats[1], F01, cfg.epipolar_band_px)
    out["pair01_paper_recipe"] = accuracy(scene, 0, 1, feats[0], feats[1], paper)
    return out


def temple_figures(folder: Path) -> dict | None:
    if not (folder / "ring_order.txt").is_file():
        return None
    order = (folder / "ring_order.txt").read_text().split()
    cams = read_middlebury_par(next(folder.glob("*_par.txt")))
    images = {n: cv2.imread(str(folder / n)) for n in order}
    feats = {n: extract_features(images[n]) for n in order}
    rows = []
    for a, b in zip(order[:-1], order[1:]):
        # Views of opposite gantry latitude are rotated 180 degrees: matched turned back.
        R_a, R_b = decompose_projection(cams[a])[1], decompose_projection(cams[b])[1]
        upright = float(R_a[1] @ R_b[1]) > 0
        if upright:
            m = match_pair(feats[a], feats[b], MatchingConfig()).matches
            x1, x2 = m.points(feats[a], feats[b])
        else:  # ZNCC is not rotation invariant: match image b turned back by 180 degrees
            turned = cv2.rotate(images[b], cv2.ROTATE_180)
            f_turned = extract_features(turned, patch_size=feats[a].patch_size)
            m = match_pair(feats[a], f_turned, MatchingConfig()).matches
            x1 = feats[a].points[m.idx1]
            h, w = turned.shape[:2]  # pixel (x, y) of the turned image is (w-1-x, h-1-y) of b
            x2 = np.array([w - 1.0, h - 1.0]) - f_turned.points[m.idx2]
        d = epipolar_distances(fundamental_from_projections(cams[a], cams[b]), x1, x2)
        rows.append({"pair": f"{a}-{b}", "upright": upright, "kept": len(m),
                     "median_epipolar_px": round(float(np.median(d)), 3) if len(m) else None})
    return {"pairs": rows, "features_per_image": int(np.median([len(f) for f in feats.values()]))}


def run() -> dict:
    cfg = MatchingConfig()
    textured0 = render_scene(SceneConfig(n_images=3))
    textured2 = render_scene(SceneConfig(n_images=3, noise_sigma=2.0))
    plain = render_scene(SceneConfig(n_images=3, textured=False))

    img0, img1, img2 = textured2.images[:3]
    F01 = fundamental_from_projections(textured2.P[0], textured2.P[1])
    fcfg = FeatureConfig()

    def known_F_pair():
        a, b = extract_features(img0, fcfg), extract_features(img1, fcfg)
        return match_pair(a, b, cfg, F=F01).matches

    def robust_pair():
        a, b = extract_features(img1, fcfg), extract_features(img2, fcfg)
        return match_pair(a, b, cfg).matches

    timing = {
        "detect_describe_one_image_s": best_time(lambda: extract_features(img0, fcfg)),
        "pair_known_F_s": best_time(known_F_pair),
        "pair_robust_F_s": best_time(robust_pair),
        "note": "best of 7 after a warm-up; 640x480, textured box, noise 2 grey levels",
    }
    data = shared_data_dir()  # $STEREOSEED_DATA, else ../shared/data
    return {
        "timing": timing,
        "textured_sigma0": scene_figures(textured0, cfg),
        "textured_sigma2": scene_figures(textured2, cfg),
        "plain_box": scene_figures(plain, cfg),
        "temple": temple_figures(data / "templeSparseRing"),
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
