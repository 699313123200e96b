"""`make bench` section `dense_real`: the quasi-dense cloud of real photos (fountain-P11, 768 x 512,
the published cameras) against a photogrammetric reference built from the full-resolution photos.

The reference (cached in ``$STEREOSEED_BENCH_CACHE``, default ``bench_output/cache``): OpenCV SIFT
on the 3072 x 2048 originals, matched between views at most three apart (ratio test) and kept
when within REF_EPIPOLAR_PX of the published epipolar line, chained into tracks, and every track
of >= 3 views (one keypoint each) triangulated with the published cameras and kept when it
reprojects within REF_REPROJECTION_PX in every view. Not a scan: its own error is about the
full-resolution matching's (a fraction of a pixel at 3072 px, ~0.03 % of the distance).

How a dense point is judged (docs/dense.md): it is compared with the reference point seen in some
view whose image lies within JUDGE_PX (768-pixel units) of the dense point's image in that view
and not farther from that view by more than 1 % (behind it, the dense point may be hidden from
that view, which sees the reference point: no verdict); of the reference points so near, the
nearest in 3D. Unjudged points have no reference point near them. Its error:
the distance from the reference point to the dense point's tangent plane (its normal), which
does not count the lateral offset of up to JUDGE_PX; "beyond": the 3D distance to that reference
point exceeds 1 % of the reference's distance to the camera. Completeness: the share of
reference points with a dense point within 1 % of their distance.

    python benchmarks/bench_dense_real.py        # prints the JSON
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from stereoseed.config import Config
from stereoseed.dense.densify import densify
from stereoseed.geometry.projection import camera_center, epipolar_distances, fundamental_from_projections
from stereoseed.io.files import read_middlebury_par
from stereoseed.io.ply import read_dense_ply
from stereoseed.io.sample_data import find_sample, missing_message
from stereoseed.pipeline import load_sequence, reconstruct

SET = "strechaFountainP11"
REF_EPIPOLAR_PX = 2.0  # full-resolution pixels: SIFT's localisation at 3072 px is ~0.3 px
REF_RATIO = 0.8  # Lowe's ratio test
REF_SIFT_CONTRAST = 0.01  # OpenCV: 0.04; the originals are soft at full size: 4,500 keypoints an image at 0.04
REF_MAX_GAP = 3  # views matched at most this far apart in the walk (wider: little overlap)
REF_REPROJECTION_PX = 1.0  # full-resolution pixels, every view of the track
JUDGE_PX = 1.0  # 768-pixel units: a dense point judged against a reference point this near in an image
FULL_DENSE_RESOLUTION = 1536  # the originals' longer side halved: the dense stage's memory within 3 GB
REF_VERSION = 2  # bump when the reference's recipe changes (the cache is rebuilt)


def cache_dir() -> Path:
    """Where the reference is kept between runs: $STEREOSEED_BENCH_CACHE, else bench_output/cache
    (next to make bench's bench.json; not in the repository)."""
    path = Path(os.environ.get("STEREOSEED_BENCH_CACHE", "bench_output/cache"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def _sift(path: Path) -> tuple[np.ndarray, np.ndarray]:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    kp, desc = cv2.SIFT_create(contrastThreshold=REF_SIFT_CONTRAST).detectAndCompute(gray, None)
    return np.array([k.pt for k in kp], np.float64), desc


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def build_reference(folder: Path) -> dict[str, np.ndarray]:
    """SIFT tracks of >= 3 views on the full-resolution photos, triangulated with the published
    cameras: points (M, 3) and seen (M, V) bool, in the published frame (metres)."""
    full = folder / "full"
    par = read_middlebury_par(full / f"{SET}_full_par.txt")
    names = [n.strip() for n in (folder / "ring_order.txt").read_text().split() if n.strip()]
    Ps = [par[n] for n in names]
    feats = [_sift(full / n) for n in names]
    offsets = np.cumsum([0] + [len(f[0]) for f in feats])
    parent = np.arange(offsets[-1])
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    for i in range(len(names)):
        for j in range(i + 1, min(i + REF_MAX_GAP + 1, len(names))):
            knn = flann.knnMatch(feats[i][1], feats[j][1], k=2)
            good = np.array([(m[0].queryIdx, m[0].trainIdx) for m in knn
                             if len(m) == 2 and m[0].distance < REF_RATIO * m[1].distance], np.int64).reshape(-1, 2)
            xa, xb = feats[i][0][good[:, 0]], feats[j][0][good[:, 1]]
            good = good[epipolar_distances(fundamental_from_projections(Ps[i], Ps[j]), xa, xb) <= REF_EPIPOLAR_PX]
            for a, b in good:
                ra, rb = _find(parent, offsets[i] + a), _find(parent, offsets[j] + b)
                if ra != rb:
                    parent[rb] = ra
    roots = np.array([_find(parent, k) for k in range(offsets[-1])])
    view_of = np.repeat(np.arange(len(names)), np.diff(offsets))
    order = np.argsort(roots, kind="stable")
    cut = np.flatnonzero(np.diff(roots[order])) + 1
    points, seen = [], []
    for members in np.split(order, cut):
        views = view_of[members]
        if len(members) < 3 or len(np.unique(views)) != len(views):
            continue
        xs = np.stack([feats[v][0][m - offsets[v]] for v, m in zip(views, members)])
        A = np.concatenate([[x[0] * Ps[v][2] - Ps[v][0], x[1] * Ps[v][2] - Ps[v][1]] for v, x in zip(views, xs)])
        X = np.linalg.svd(A / np.linalg.norm(A, axis=1, keepdims=True))[2][-1]
        if abs(X[3]) < 1e-12:
            continue
        X = X[:3] / X[3]
        proj = np.stack([Ps[v] @ np.r_[X, 1.0] for v in views])
        if np.any(proj[:, 2] <= 0) or np.any(np.linalg.norm(proj[:, :2] / proj[:, 2:] - xs, axis=1) > REF_REPROJECTION_PX):
            continue
        mask = np.zeros(len(names), bool)
        mask[views] = True
        points.append(X)
        seen.append(mask)
    return {"points": np.array(points), "seen": np.array(seen), "version": np.array(REF_VERSION)}


def reference(folder: Path) -> dict[str, np.ndarray]:
    path = cache_dir() / f"{SET}_reference.npz"
    if path.is_file():
        ref = dict(np.load(path))
        if int(ref.get("version", -1)) == REF_VERSION:
            return ref
    ref = build_reference(folder)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **ref)
    tmp.replace(path)
    return ref


def judge(points: np.ndarray, normals: np.ndarray, ref: dict[str, np.ndarray], Ps: list[np.ndarray],
          size: tuple[int, int]) -> dict[str, float]:
    """The cloud's figures against the reference (module doc): Ps the published cameras of the
    images the points were made from (size (W, H))."""
    R, seen = ref["points"], ref["seen"]
    best = np.full(len(points), np.inf)  # 3D distance to the nearest candidate reference point
    match = np.full(len(points), -1)
    match_dist = np.zeros(len(points))
    for v, P in enumerate(Ps):
        rows = np.flatnonzero(seen[:, v])
        hr = np.c_[R[rows], np.ones(len(rows))] @ P.T
        tree = cKDTree(hr[:, :2] / hr[:, 2:])
        hp = np.c_[points, np.ones(len(points))] @ P.T
        xy = hp[:, :2] / np.maximum(hp[:, 2:], 1e-12)
        inside = (hp[:, 2] > 0) & (xy[:, 0] >= -0.5) & (xy[:, 1] >= -0.5) & (xy[:, 0] < size[0]) & (xy[:, 1] < size[1])
        d, k = tree.query(xy[inside], distance_upper_bound=JUDGE_PX)
        idx = np.flatnonzero(inside)[d <= JUDGE_PX]
        cand = rows[k[d <= JUDGE_PX]]
        gap = np.linalg.norm(points[idx] - R[cand], axis=1)
        # a dense point behind the reference point this view sees may be hidden from it: no verdict here
        behind = hp[idx, 2] - hr[k[d <= JUDGE_PX], 2] > 0.01 * hr[k[d <= JUDGE_PX], 2]
        gap[behind] = np.inf
        better = gap < best[idx]
        best[idx[better]] = gap[better]
        match[idx[better]] = cand[better]
        match_dist[idx[better]] = np.linalg.norm(R[cand[better]] - camera_center(P), axis=1)
    judged = np.flatnonzero(match >= 0)
    offset = points[judged] - R[match[judged]]
    plane = np.abs(np.einsum("ij,ij->i", offset, normals[judged]))
    beyond = np.linalg.norm(offset, axis=1) > 0.01 * match_dist[judged]
    centres = np.array([camera_center(P) for P in Ps])
    ref_dist = np.array([np.linalg.norm(centres[s] - x, axis=1).mean() for x, s in zip(R, seen)])
    near = cKDTree(points).query(R)[0] if len(points) else np.full(len(R), np.inf)
    return {"points": int(len(points)), "reference_points": int(len(R)), "judged": int(len(judged)),
            "accuracy_median_mm": float(np.median(plane) * 1000), "accuracy_p90_mm": float(np.percentile(plane, 90) * 1000),
            "beyond_1pct_share": float(beyond.mean()),
            "completeness_1pct": float(np.mean(near <= 0.01 * ref_dist)),
            "median_distance_m": float(np.median(ref_dist))}


def published_run(folder: Path, cfg: Config, par_name: str = f"{SET}_par.txt"):
    """The sparse run of the walk (the pair's published cameras), every registered camera then
    replaced by its published one: the dense stage judged alone, not the camera estimates."""
    images, names, P_pair = load_sequence(str(folder / "ring_order.txt"), str(folder / par_name))
    recon, _ = reconstruct(images, names, P_pair, cfg)
    par = read_middlebury_par(folder / par_name)
    for v in recon.registered_views:
        recon.views[v].P = par[recon.views[v].name]
    return recon


def _peak_mb() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return float(max(own, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024))


def sampled_run(args: list[str]) -> dict:
    """Run a command to its end in a child process: its seconds, exit code, the end of its stderr,
    and the peak memory of it and its children together (proportional set size sampled every
    0.5 s: the pages they share counted once)."""
    import psutil

    with tempfile.TemporaryFile("w+") as err:  # a file, not a pipe: a long stderr cannot block the child
        t = time.perf_counter()
        child = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=err, text=True)
        me, peak = psutil.Process(child.pid), 0.0
        while child.poll() is None:
            try:
                peak = max(peak, sum(p.memory_full_info().pss for p in [me, *me.children(recursive=True)]) / 2**20)
            except psutil.Error:  # a worker gone between the listing and the reading
                pass
            time.sleep(0.5)
        seconds = time.perf_counter() - t
        err.seek(0)
        stderr = err.read()
    return {"seconds": seconds, "exit": child.returncode, "peak_pss_mib": peak, "stderr_end": stderr[-1500:]}


def whole_command(full: Path, ref: dict, Ps: list[np.ndarray], size: tuple[int, int]) -> dict:
    """``stereoseed reconstruct full/ --dense`` on the 3072 x 2048 originals as a user runs it (its
    own cameras, the dense stage at full resolution), in a child process (:func:`sampled_run`),
    and its cloud judged as the others."""
    with tempfile.TemporaryDirectory() as tmp:
        run = sampled_run([str(Path(sys.executable).parent / "stereoseed"), "reconstruct", str(full), "--calib",
                           str(full / f"{SET}_full_par.txt"), "--unit", "m", "--dense", "--out", tmp, "--quiet"])
        if run["exit"] != 0:
            return run
        points, _, normals, _, _ = read_dense_ply(Path(tmp) / "dense.ply")
        return {"seconds": run["seconds"], "peak_pss_mib": run["peak_pss_mib"], "points": int(len(points)),
                **judge(points, normals, ref, Ps, size)}


def run() -> dict:
    folder = find_sample(SET)
    if folder is None:
        return {"skipped": missing_message(SET)}
    t = time.perf_counter()
    ref = reference(folder)
    out = {"reference_seconds": time.perf_counter() - t, "reference_points": int(len(ref["points"])),
           "reference_views_per_point": float(ref["seen"].sum(axis=1).mean())}
    cfg = Config()
    recon = published_run(folder, cfg)
    Ps = [recon.views[v].P for v in range(len(recon.views))]
    size = recon.views[0].image_size
    densify(recon, cfg)  # warm-up: JIT caches and worker start-up
    # the default, and without the multi-view check (2 views: every pair's point, as before issue 50)
    no_check = cfg.replace(dense={"min_support": 2, "min_confidence": 0.0})
    for label, c in (("768x512", cfg), ("768x512_no_multiview_check", no_check)):
        t = time.perf_counter()
        cloud, report = densify(recon, c)
        out[label] = {"seconds": time.perf_counter() - t, "fusion_seconds": report["fusion_seconds"],
                      "points_before_fusion": report["points_before_fusion"],
                      "points_unjudged": report["points_unjudged"],
                      **judge(cloud.points, cloud.normals, ref, Ps, size)}
    out["peak_rss_mb"] = _peak_mb()
    # the 3072 x 2048 originals: the sparse run on them, the dense stage at --dense-resolution
    # FULL_DENSE_RESOLUTION
    full = published_run(folder / "full", cfg, f"{SET}_full_par.txt")
    del recon
    c = cfg.replace(dense={"resolution": FULL_DENSE_RESOLUTION})
    t = time.perf_counter()
    cloud, report = densify(full, c)
    out[f"3072x2048_at_{FULL_DENSE_RESOLUTION}"] = {
        "seconds": time.perf_counter() - t, "fusion_seconds": report["fusion_seconds"],
        "points_before_fusion": report["points_before_fusion"], "peak_memory_mb": report["peak_memory_mb"],
        **judge(cloud.points, cloud.normals, ref, Ps, size)}
    # last: the child's peak would count in this process's children's peak above
    out["3072x2048_whole_command"] = whole_command(folder / "full", ref, Ps, size)
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
