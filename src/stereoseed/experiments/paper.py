"""Reproduce the paper's experiments (§5): Fig. 7, 8, 9 and analogues of Tables 2 and 3, plus the
comparison the paper draws against global bundle adjustment.

    run_paper_bench("paper_bench")              # full run (< 10 min on 2 cores)
    run_paper_bench("paper_bench", quick=True)  # short sequences of half-size images (~20 s), same outputs

Four pipeline variants are compared (:data:`VARIANTS`): the paper's local BA, a global BA after
every insertion (Pollefeys; Fitzgibbon & Zisserman, the paper's foils), local BA plus one final
global BA, and our accurate mode.

How the work is organised:

* Each scene is rendered once. The ring of views at 20° (the paper's 14 images, and the closed
  18-image ring) is rendered once at its longest length: the synthetic module guarantees that the
  number of images does not move the cameras, so every shorter sequence is a prefix of it. The
  noisy rings of Fig. 9 are derived from the noise-free renders with the renderer's own noise
  stream (:func:`noisy_images`), byte-identical to ``render_scene(SceneConfig(noise_sigma=s))``.
* Every reconstruction whose result does not depend on timing (Fig. 7, Fig. 9, the tables) is a
  job run in a pool of ``workers`` spawned processes; jobs asked for by several figures are run
  once. Fig. 8 measures time, so its runs happen in this process alone, before the pool starts.
* A sequence of n images is evaluated as a run on its first n images gives it: with a global BA,
  later insertions move earlier cameras, so the cameras 0..n-1 at the end of a longer run would
  not measure that. One run per sequence, noise level and variant serves every count: after the
  n-th image, the finishing step runs on the model, which is then put back
  (:func:`stereoseed.pipeline.as_finished`; the incremental loop never looks ahead, so this is
  the n-image run's result, to the last bit) and the run goes on.
* An insertion that fails is reported by the pipeline and skipped; a run that cannot even start
  (:class:`StereoseedError`) is recorded with its message and its numbers are NaN (``null`` in
  the JSON). Nothing here works around such failures.

Outputs in ``out_dir``: ``fig7_rms_vs_images.png``, ``fig8_time_vs_images.png``,
``fig9_rms_vs_noise.png``, ``table2_progression.png``, ``paper_bench.json`` (every figure's data)
and ``summary.md`` (Markdown tables); the figures and tables are drawn by
:mod:`stereoseed.experiments.report`.
"""
from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from stereoseed.config import Config

from stereoseed.sfm.config import PipelineConfig
from stereoseed.errors import StereoseedError
from stereoseed.experiments.report import LABELS, json_clean, plot_fig7, plot_fig8, plot_fig9, plot_table2, summary_md
from stereoseed.io.files import write_json, write_text

__all__ = ["VARIANTS", "BenchPlan", "FULL_PLAN", "QUICK_PLAN", "run_paper_bench", "noisy_images",
           "shared_data_dir"]

# ---------------------------------------------------------------------------------------------
# What is compared

VARIANTS: dict[str, PipelineConfig] = {
    "local": PipelineConfig(mode="paper", ba="local"),
    "global": PipelineConfig(mode="paper", ba="global"),
    "final": PipelineConfig(mode="paper", ba="final"),
    "accurate": PipelineConfig(mode="accurate"),
}
TABLE_VARIANTS = ("local", "accurate")  # the two modes of the pipeline


@dataclass(frozen=True)
class BenchPlan:
    """Sizes of every experiment. :data:`FULL_PLAN` reproduces the paper; :data:`QUICK_PLAN`
    runs the same code on short sequences of half-size images (for tests)."""

    ring_images: int  # images rendered of the 20° ring: covers the 14- and 18-image sequences
    fig7_images: int  # the paper's 14 images
    fig7_counts: tuple[int, ...]  # sequence lengths evaluated in Fig. 7 (runs on the first n images)
    fig8_images: int  # the long ring of Fig. 8
    fig8_step_deg: float
    fig9_images: int
    fig9_sigmas: tuple[float, ...]  # grey levels (0..255)
    fig9_seeds: int  # scenes per noise level (each seed: other poses, texture and noise)
    fig9_variants: tuple[str, ...]
    box14_images: int  # table sequences: the 14-image ring ...
    box18_images: int  # ... the closed 18-image ring ...
    temple_images: int | None  # ... and templeSparseRing (None: all 16)
    dense_sequences: tuple[str, ...]  # sequences whose full-length runs are densified ...
    dense_variants: tuple[str, ...]  # ... with these variants
    quick: bool = False
    scene_scale: float = 1.0  # rendered image size and focal lengths, relative to the paper's 640 x 480


FULL_PLAN = BenchPlan(
    ring_images=18, fig7_images=14, fig7_counts=(2, 4, 6, 8, 10, 12, 14),  # every n from 2 to 14: ~35 s more
    fig8_images=36, fig8_step_deg=10.0,
    fig9_images=14, fig9_sigmas=(0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0), fig9_seeds=5,
    fig9_variants=("local", "accurate"),
    box14_images=14, box18_images=18, temple_images=None,
    dense_sequences=("box14", "box18", "temple"), dense_variants=TABLE_VARIANTS,
)
QUICK_PLAN = BenchPlan(
    ring_images=8, fig7_images=6, fig7_counts=(2, 4, 6),
    fig8_images=6, fig8_step_deg=10.0,
    fig9_images=4, fig9_sigmas=(0.0, 2.0), fig9_seeds=2,
    fig9_variants=("local", "accurate"),
    box14_images=6, box18_images=8, temple_images=6,
    dense_sequences=("box14",), dense_variants=("local",), quick=True, scene_scale=0.5,
)

SEQUENCE_TITLES = {"box14": "synthetic box, 14-image ring", "box18": "synthetic box, 18-image closed ring",
                   "temple": "Middlebury templeSparseRing"}


def shared_data_dir() -> Path:
    """Folder of the real sequences: $STEREOSEED_DATA, else ``shared/data`` beside the checkout
    (src/stereoseed/__init__.py -> the folder holding the repository)."""
    from stereoseed.io.sample_data import offline_mirror

    return offline_mirror()


def _progression(n: int) -> tuple[int, ...]:
    """Table 2's image counts: 4, 8, 12 as in the paper, then the whole sequence."""
    return tuple(sorted({c for c in (4, 8, 12) if c < n} | {n}))


# ---------------------------------------------------------------------------------------------
# Scenes


def noisy_images(images: list[np.ndarray], sigma: float, scene_seed: int) -> list[np.ndarray]:
    """The images of ``render_scene(SceneConfig(noise_sigma=sigma, seed=scene_seed, ...))`` made
    from the noise-free render of the same config: the renderer adds noise after rendering, from
    a stream of its own, so re-rendering each noise level would only repeat the ray tracing."""
    from stereoseed.synthetic.scene import noise_generator
    from stereoseed.synthetic.render import add_noise

    if sigma <= 0:
        return list(images)
    return [add_noise(im, sigma, noise_generator(scene_seed, i)) for i, im in enumerate(images)]


@dataclass
class _Sequence:
    """An ordered sequence the pipeline can run on, with ground truth when synthetic."""

    images: list
    names: list
    P_pair: list
    scene_seed: int | None = None  # synthetic only (noise stream)
    P_true: list | None = None
    corners: np.ndarray | None = None
    visibility: list | None = None

    def prefix(self, n: int) -> "_Sequence":
        """The first n images (a job ships only what it uses to its worker)."""
        cut = (lambda xs: None if xs is None else list(xs[:n]))
        return _Sequence(list(self.images[:n]), list(self.names[:n]), self.P_pair, self.scene_seed,
                         cut(self.P_true), self.corners, cut(self.visibility))


def _synthetic_sequence(scene: Any) -> _Sequence:
    return _Sequence(images=scene.images, names=scene.names, P_pair=scene.P[:2], scene_seed=scene.config.seed,
                     P_true=scene.P, corners=scene.corners,
                     visibility=[scene.corner_visibility(i) for i in range(scene.n_images)])


def _load_temple(n: int | None) -> _Sequence | None:
    seq = shared_data_dir() / "templeSparseRing"
    if not (seq / "ring_order.txt").is_file():
        return None
    from stereoseed.pipeline import load_sequence

    images, names, P_pair = load_sequence(str(seq / "ring_order.txt"), str(seq / "templeSR_par.txt"))
    n = len(images) if n is None else min(n, len(images))
    return _Sequence(images=images[:n], names=names[:n], P_pair=P_pair)


# ---------------------------------------------------------------------------------------------
# One reconstruction job (runs in a worker process)


@dataclass(frozen=True)
class _Job:
    """One pipeline run on a sequence, optionally with image noise, evaluated at the image
    counts ``counts`` (its length is the largest): the box-corner evaluation (synthetic) at
    each, the dense stage at ``dense_counts``. Picklable, for the process pool."""

    sequence: _Sequence = field(compare=False)
    counts: tuple[int, ...]
    variant: str
    seed: int
    noise_sigma: float = 0.0
    dense_counts: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return max(self.counts)

    def shipped(self) -> "_Job":
        """The job with the images it uses only (what a worker receives)."""
        return dataclasses.replace(self, sequence=self.sequence.prefix(self.n))


def _config(variant: str, seed: int) -> Config:
    # The seed also drives RANSAC, so one seed fixes every random choice of the run. The dense
    # stage runs serially: the jobs already fill the cores, and a fork pool inside a process that
    # ran OpenMP/OpenCV threads risks a deadlock.
    return Config(pipeline=VARIANTS[variant]).replace(matching={"seed": seed}, resection={"seed": seed},
                                                      dense={"workers": 1})


def _run_job(job: _Job) -> dict[int, dict[str, Any]]:
    """{count: results of a run on the first ``count`` images} for each of the job's counts. One
    run on the longest prefix: after each count's insertion, the finishing step runs on the
    model, which is then put back (:func:`stereoseed.pipeline.as_finished`): what a run on
    those images alone returns (the loop never looks ahead), at the cost of the finishing
    steps only. An error fails the counts it reaches, not those evaluated before it.
    "seconds": the run's time to that count, the other counts' evaluations left out (about a
    separate run's: the images after it are being read ahead meanwhile)."""
    from stereoseed.pipeline import as_finished, reconstruct

    seq, n = job.sequence, job.n
    images = seq.images[:n]
    if job.noise_sigma > 0:
        images = noisy_images(images, job.noise_sigma, seq.scene_seed)
    cfg = _config(job.variant, job.seed)
    out: dict[int, dict[str, Any]] = {}
    t0 = time.perf_counter()
    evaluating = 0.0  # seconds spent evaluating earlier counts: no count's run time

    def header(count: int) -> dict[str, Any]:
        return {"images": count, "variant": job.variant, "noise_sigma": job.noise_sigma}

    def evaluate(recon: Any, report: dict[str, Any], count: int, seconds: float) -> dict[str, Any]:
        r = {**header(count), **_sparse_summary(report), "seconds": seconds}
        if seq.corners is not None:
            r.update(_corner_error(recon, seq, count))
        if count in job.dense_counts:
            r.update(_dense_summary(recon, cfg, synthetic=seq.corners is not None))
        return r

    def failed(count: int, e: StereoseedError) -> dict[str, Any]:
        return {**header(count), "error": str(e), "registered": 0, "seconds": time.perf_counter() - t0}

    def after_insertion(recon: Any, per_image: list[dict[str, Any]]) -> None:
        nonlocal evaluating
        count = len(per_image)
        if count in job.counts and count < n:  # the run's own end gives the last count
            t = time.perf_counter()
            try:
                with as_finished(recon, cfg) as (model, report):
                    run_time = t - t0 - evaluating + report["final"]["seconds"]  # insertions so far, finishing step
                    out[count] = evaluate(model, report, count, run_time)
            except StereoseedError as e:  # as a run on these images would have failed
                out[count] = failed(count, e)
            evaluating += time.perf_counter() - t

    try:
        recon, report = reconstruct(images, seq.names[:n], seq.P_pair, cfg, after_insertion=after_insertion)
        out[n] = evaluate(recon, report, n, time.perf_counter() - t0 - evaluating)
    except StereoseedError as e:
        return {c: out[c] if c in out else failed(c, e) for c in job.counts}
    return out


def _sparse_summary(report: dict[str, Any]) -> dict[str, Any]:
    rep = report["reprojection"]
    return {"registered": report["registered"], "sparse_points": report["points"], "eq14": rep["eq14"],
            "rms_px": rep["rms_px"], "observations": rep.get("observations"),
            "failed_images": [r["image"] for r in report["per_image"] if r.get("status") == "failed"]}


def _corner_error(recon: Any, seq: _Sequence, n: int) -> dict[str, Any]:
    """Paper eq. 13 on the box corners, with the estimated cameras of the n images."""
    from stereoseed.experiments.evaluation import reconstruct_corners, rms_3d

    views = recon.views[:n]
    points, seen = reconstruct_corners([v.P for v in views], [v.features for v in views], seq.corners,
                                       seq.P_true[:n], seq.visibility[:n])
    rms = rms_3d(points, seq.corners[seen]) if len(seen) else math.nan
    return {"rms_3d_m": rms, "corners": int(len(seen))}


def _dense_summary(recon: Any, cfg: Config, synthetic: bool) -> dict[str, Any]:
    from stereoseed.dense.densify import densify

    cloud, rep = densify(recon, cfg)
    out = {"dense_points": rep["points"], "dense_points_before_fusion": rep["points_before_fusion"],
           "dense_seconds": rep["seconds"]}
    if synthetic and rep["points"]:
        # Ground truth for the synthetic scene: distance of each fused point to the box or ground.
        from stereoseed.experiments.evaluation import surface_distance

        d = surface_distance(cloud.points)
        # The median describes the bulk; the 90th percentile and the RMS show the stray points.
        out.update(dense_surface_median_m=float(np.median(d)), dense_surface_p90_m=float(np.percentile(d, 90)),
                   dense_surface_rms_m=float(np.sqrt(np.mean(d * d))))
    return out


def _job_cost(job: _Job) -> float:
    """Rough seconds, to start the longest jobs first (the pool then ends evenly)."""
    per_image = {"local": 0.2, "global": 0.03 * job.n, "final": 0.25, "accurate": 0.45}[job.variant]
    final_ba = sum(0.05 * c ** 2 for c in job.counts) if job.variant in ("final", "accurate") else 0.0
    return job.n * per_image + final_ba + sum(0.5 * c for c in job.dense_counts)


# ---------------------------------------------------------------------------------------------
# Fig. 8: timed runs, in this process


def _timed_run(seq: _Sequence, variant: str, seed: int) -> dict[str, Any]:
    """Wall-clock time after each insertion, taken from the pipeline's progress callback: this
    counts failed insertions too (the per-image report has no time for them)."""
    from stereoseed.pipeline import reconstruct

    stamps: dict[int, float] = {}
    t0 = time.perf_counter()

    def mark(done: int, total: int, message: str) -> None:
        stamps[done] = time.perf_counter() - t0

    try:
        _, report = reconstruct(seq.images, seq.names, seq.P_pair, _config(variant, seed), progress=mark)
    except StereoseedError as e:
        return {"error": str(e), "total_s": None}
    total = time.perf_counter() - t0
    n = len(seq.images)
    counts = list(range(2, n + 1))
    cumulative = [stamps.get(c, math.nan) for c in counts]
    per_insertion = list(np.diff(cumulative))  # insertion of the image that makes the count c (c >= 3)
    bundle = [r["seconds"].get("bundle", math.nan) if r.get("status") == "registered" else math.nan
              for r in report["per_image"][2:]]
    return {
        "images": counts, "cumulative_s": cumulative,
        "insertion_images": counts[1:], "per_insertion_s": per_insertion, "per_insertion_bundle_s": bundle,
        "first_insertion_s": per_insertion[0] if per_insertion else math.nan,
        "last_insertion_s": per_insertion[-1] if per_insertion else math.nan,
        "finish_s": total - cumulative[-1],  # final global BA / loop closure, after the last insertion
        "finish_step": "loop closure" if report["final"].get("loop_closure", {}).get("closed")
        else "final global BA" if "final_ba" in report["final"] else None,
        "total_s": total, "registered": report["registered"],
        "failed_images": [r["image"] for r in report["per_image"] if r.get("status") == "failed"],
    }


# ---------------------------------------------------------------------------------------------
# The bench


class _Jobs:
    """The reconstruction jobs: one run per sequence, noise level and variant, evaluated at
    every image count a figure or table asks for."""

    def __init__(self, seed: int):
        self.seed = seed
        self.jobs: dict[tuple, _Job] = {}

    def want(self, seq_key: tuple, seq: _Sequence, n: int, variant: str, sigma: float = 0.0,
             dense: bool = False) -> tuple:
        """The key of the results of a run on the first n images (``results[key]``)."""
        run = (*seq_key, float(sigma), variant)
        job = self.jobs.get(run, _Job(seq, (), variant, self.seed, float(sigma)))
        dense_counts = {*job.dense_counts, n} if dense else set(job.dense_counts)
        self.jobs[run] = dataclasses.replace(job, counts=tuple(sorted({*job.counts, n})),
                                             dense_counts=tuple(sorted(dense_counts)))
        return (*seq_key, float(sigma), n, variant)


def _run_pool(jobs: dict[tuple, _Job], workers: int, tick: Callable[[str], None]) -> dict[tuple, dict]:
    """{(*sequence key, sigma, n, variant): results} of every job, for each of its counts."""
    order = sorted(jobs, key=lambda k: -_job_cost(jobs[k]))
    results: dict[tuple, dict] = {}

    def done(run: tuple, by_count: dict[int, dict]) -> None:
        for count, r in by_count.items():
            results[(*run[:-1], count, run[-1])] = r
        tick(f"{run[-1]}, {jobs[run].n} images")

    if workers <= 1:
        for run in order:
            done(run, _run_job(jobs[run].shipped()))
        return results
    # "spawn": the workers start clean instead of inheriting this process's OpenMP (renderer) and
    # OpenCV thread pools, which are not fork-safe.
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)
    try:
        futures = {pool.submit(_run_job, jobs[run].shipped()): run for run in order}
        for fut in as_completed(futures):
            done(futures[fut], fut.result())
    except BaseException:
        # A bug in a run (or Ctrl-C): report it now rather than after every queued job has run.
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return results


def run_paper_bench(out_dir: str | os.PathLike, quick: bool = False, seed: int = 0, progress: bool = True,
                    workers: int = 2) -> dict[str, Any]:
    """Run every experiment, write the figures, ``paper_bench.json`` and ``summary.md`` in
    out_dir, and return the JSON's content.

    quick: short sequences (:data:`QUICK_PLAN`, about a minute) instead of the paper's
    (:data:`FULL_PLAN`, under ten minutes on 2 cores). seed: scenes, image noise and RANSAC
    (same seed, same numbers; times vary). progress: one tqdm bar on stderr. workers: processes
    for the untimed runs (the target machine has 2 cores); they are spawned, so a script calling
    this needs the usual ``if __name__ == "__main__":`` guard (workers=1 runs all in this process).
    """
    from tqdm import tqdm

    t_start = time.perf_counter()
    plan = QUICK_PLAN if quick else FULL_PLAN
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_renders = 2 + (plan.fig9_seeds - 1) + 1  # ring, long ring, other seeds, temple
    with tqdm(total=n_renders, unit="step", file=sys.stderr, disable=not progress, desc="paper bench") as bar:
        layout, fig8, results = _run_all(plan, seed, bar, workers)
    data = _assemble(plan, seed, layout, fig8, results)
    plot_fig7(data["fig7"], out / "fig7_rms_vs_images.png")
    plot_fig8(data["fig8"], out / "fig8_time_vs_images.png")
    plot_fig9(data["fig9"], out / "fig9_rms_vs_noise.png")
    plot_table2(data["table2"], out / "table2_progression.png")
    data["seconds"] = time.perf_counter() - t_start
    data["files"] = ["fig7_rms_vs_images.png", "fig8_time_vs_images.png", "fig9_rms_vs_noise.png",
                     "table2_progression.png", "paper_bench.json", "summary.md"]
    data = json_clean(data)
    write_json(out / "paper_bench.json", data)
    write_text(out / "summary.md", summary_md(data))
    return data


def _run_all(plan: BenchPlan, seed: int, bar: Any, workers: int) -> tuple[dict[str, Any], dict, dict]:
    """Render, time Fig. 8, run the jobs. Returns (which job each figure and table uses, Fig. 8 runs, job results)."""
    from stereoseed.synthetic.scene import SceneConfig, render_scene

    def tick(message: str) -> None:
        bar.set_postfix_str(message[:48])
        bar.update(1)

    # 1. scenes, each rendered once
    def scene_config(**kw: Any) -> SceneConfig:  # the plan's image size, the same field of view
        return SceneConfig(**kw).scaled(plan.scene_scale)

    ring_cfg = scene_config(n_images=plan.ring_images, seed=seed)
    ring = _synthetic_sequence(render_scene(ring_cfg))
    tick("rendered the 20° ring")
    long_cfg = scene_config(n_images=plan.fig8_images, step_deg=plan.fig8_step_deg, seed=seed)
    long_ring = _synthetic_sequence(render_scene(long_cfg))
    tick(f"rendered the {plan.fig8_images}-image ring")
    seeds = [seed + j for j in range(plan.fig9_seeds)]
    noise_rings = {seed: ring}
    for s in seeds[1:]:
        noise_rings[s] = _synthetic_sequence(render_scene(scene_config(n_images=plan.fig9_images, seed=s)))
        tick(f"rendered scene seed {s}")
    temple = _load_temple(plan.temple_images)
    tick("loaded templeSparseRing" if temple else "templeSparseRing not found")

    # 2. the untimed jobs: every figure and table says which runs it needs
    jobs = _Jobs(seed)
    ring_key = ("box", 20.0, seed)
    fig7_keys = {v: [jobs.want(ring_key, ring, n, v) for n in plan.fig7_counts] for v in VARIANTS}
    fig9_keys = {v: [[jobs.want(("box", 20.0, s), noise_rings[s], plan.fig9_images, v, sigma) for s in seeds]
                     for sigma in plan.fig9_sigmas] for v in plan.fig9_variants}
    sequences: dict[str, tuple[tuple, _Sequence, int]] = {
        "box14": (ring_key, ring, plan.box14_images), "box18": (ring_key, ring, plan.box18_images)}
    if temple is not None:
        sequences["temple"] = (("temple",), temple, len(temple.images))
    table_keys: dict[str, dict[str, list[tuple]]] = {}
    for name, (key, seq, n) in sequences.items():
        table_keys[name] = {v: [jobs.want(key, seq, c, v, dense=(c == n and name in plan.dense_sequences
                                                                   and v in plan.dense_variants))
                                for c in _progression(n)] for v in TABLE_VARIANTS}
    bar.total += len(VARIANTS) + 1 + len(jobs.jobs)
    bar.refresh()

    # 3. Fig. 8, alone on the machine: timings are the point
    fig8 = _fig8(long_ring, seed, tick)

    # 4. everything else, in parallel
    results = _run_pool(jobs.jobs, workers, tick)
    layout = {"ring_cfg": ring_cfg, "long_cfg": long_cfg, "seeds": seeds, "fig7_keys": fig7_keys,
              "fig9_keys": fig9_keys, "table_keys": table_keys, "sequences": sequences,
              "has_temple": temple is not None}
    return layout, fig8, results


def _fig8(long_ring: _Sequence, seed: int, tick: Callable[[str], None]) -> dict[str, Any]:
    # Warm-up on three images: the first run of each code path loads its compiled Numba kernels
    # (and OpenCV's), which would be charged to whichever variant happens to use it first.
    warm = _Sequence(long_ring.images[:3], long_ring.names[:3], long_ring.P_pair)
    for v in VARIANTS:
        _timed_run(warm, v, seed)
    tick("warm-up")
    runs = {}
    for v in VARIANTS:
        runs[v] = _timed_run(long_ring, v, seed)
        tick(f"Fig. 8 timing: {v}")
    return runs


# ---------------------------------------------------------------------------------------------
# Assembling the data


def _get(results: dict[tuple, dict], key: tuple, field_: str) -> Any:
    value = results[key].get(field_)
    return math.nan if value is None else value


def _stats(values: list[float]) -> dict[str, Any]:
    a = np.array([math.nan if v is None else v for v in values], dtype=float)
    ok = a[np.isfinite(a)]
    if len(ok) == 0:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan, "valid": 0}
    # Sample standard deviation: the seeds are a sample of scenes, not the whole population.
    std = float(np.std(ok, ddof=1)) if len(ok) > 1 else 0.0
    return {"mean": float(ok.mean()), "std": std, "min": float(ok.min()), "max": float(ok.max()), "valid": int(len(ok))}


def _assemble(plan: BenchPlan, seed: int, layout: dict[str, Any], fig8: dict, results: dict) -> dict[str, Any]:
    ring_cfg, long_cfg, seeds = layout["ring_cfg"], layout["long_cfg"], layout["seeds"]
    fig7_keys, fig9_keys, table_keys = layout["fig7_keys"], layout["fig9_keys"], layout["table_keys"]
    sequences, has_temple = layout["sequences"], layout["has_temple"]
    fig7 = {
        "description": "3D RMS (eq. 13, metres, no alignment) of the box corners triangulated with the estimated "
                       "cameras, against the number of images; each point is a run on the first n images",
        "scene": dataclasses.asdict(dataclasses.replace(ring_cfg, n_images=plan.fig7_images)),
        "images": list(plan.fig7_counts),
        "rms_3d_m": {v: [_get(results, k, "rms_3d_m") for k in keys] for v, keys in fig7_keys.items()},
        "corners": {v: [results[k].get("corners") for k in keys] for v, keys in fig7_keys.items()},
        "registered": {v: [results[k].get("registered") for k in keys] for v, keys in fig7_keys.items()},
        "errors": {v: [results[k].get("error") for k in keys if results[k].get("error")] for v, keys in fig7_keys.items()},
    }
    local_t, global_t = fig8["local"].get("total_s"), fig8["global"].get("total_s")
    ratio = global_t / local_t if local_t and global_t else math.nan
    fig8_data = {
        "description": "wall-clock seconds to reconstruct the first n images (one run per variant; the pipeline is "
                       "incremental, so the time after n images is that of a run on n images), the time of each "
                       "insertion, and the finishing step (final global BA or loop closure) after the last one",
        "scene": dataclasses.asdict(long_cfg), "variants": fig8, "global_local_time_ratio": ratio,
    }
    fig9 = {
        "description": "3D RMS (eq. 13, metres) of the box corners against Gaussian image noise (grey levels, "
                       "0..255); one run per noise level and scene seed",
        "images": plan.fig9_images, "sigmas": list(plan.fig9_sigmas), "seeds": seeds, "variants": {},
    }
    for v, grid in fig9_keys.items():
        values = [[_get(results, k, "rms_3d_m") for k in row] for row in grid]
        stats = [_stats(row) for row in values]
        fig9["variants"][v] = {
            "rms_3d_m": values,  # [noise level][seed]
            "mean_m": [st["mean"] for st in stats], "std_m": [st["std"] for st in stats],
            "min_m": [st["min"] for st in stats], "max_m": [st["max"] for st in stats],
            "valid": [st["valid"] for st in stats],
            "failed_images": [[len(results[k].get("failed_images") or []) for k in row] for row in grid],
        }
    table2, table3 = [], []
    for name, per_variant in table_keys.items():
        n_full = sequences[name][2]
        for v, keys in per_variant.items():
            for k in keys:
                r = results[k]
                row = {"sequence": name, "title": SEQUENCE_TITLES[name], "variant": v, "images": k[-2],
                       "registered": r.get("registered"), "sparse_points": r.get("sparse_points"),
                       "eq14": r.get("eq14"), "rms_px": r.get("rms_px"), "rms_3d_m": r.get("rms_3d_m"),
                       "failed_images": r.get("failed_images", []), "error": r.get("error")}
                table2.append(row)
                if k[-2] == n_full:
                    table3.append({**row, **{f: r.get(f) for f in ("dense_points", "dense_points_before_fusion",
                                                                   "dense_seconds", "dense_surface_median_m",
                                                                   "dense_surface_p90_m", "dense_surface_rms_m")}})
    return {
        "schema": "stereoseed.paper_bench/1", "quick": plan.quick, "seed": seed,
        "plan": dataclasses.asdict(plan),
        "variants": {v: {"label": LABELS[v], "pipeline": dataclasses.asdict(pc)} for v, pc in VARIANTS.items()},
        "global_local_time_ratio": ratio,
        "fig7": fig7, "fig8": fig8_data, "fig9": fig9,
        "table2": {"description": "sparse reconstruction as images are added (paper Table 2); eq14 is the paper's "
                                  "error (squared pixels over images x points), rms_px the RMS over observations",
                   "rows": table2},
        "table3": {"description": "quasi-dense reconstruction of each whole sequence (paper Table 3); the dense "
                                  "distance to the true surface exists for the synthetic scenes only",
                   "rows": table3},
        "runs": [{"sequence": list(k[:-3]), "noise_sigma": k[-3], "images": k[-2], "variant": k[-1],
                  **{f: r.get(f) for f in ("registered", "seconds", "error")}}
                 for k, r in results.items()],
        "temple_found": has_temple,
        "data_dir": str(shared_data_dir()),
    }
