"""Figures and Markdown summary of the paper bench (:mod:`stereoseed.experiments.paper`).

Every function takes the bench's JSON-able data (``paper_bench.json``: metres and seconds, None
for a missing value) and writes or returns one output: ``plot_fig7``, ``plot_fig8``,
``plot_fig9``, ``plot_table2`` a PNG each (Matplotlib's Agg canvas, no pyplot state),
``summary_md`` the Markdown tables; ``json_clean`` makes the data strict JSON.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.io.files import atomic_path

# How each pipeline variant (experiments.VARIANTS) is named in legends and tables.
LABELS = {
    "local": "paper: local BA (eq. 12)",
    "global": "paper + global BA after every insertion",
    "final": "paper + one final global BA",
    "accurate": "accurate mode",
}
# One colour and marker per variant in every figure, so the figures read together.
STYLE = {
    "local": {"color": "tab:blue", "marker": "o"},
    "global": {"color": "tab:red", "marker": "s"},
    "final": {"color": "tab:green", "marker": "^"},
    "accurate": {"color": "tab:orange", "marker": "D"},
}


def _arr(values: list, scale: float = 1.0) -> np.ndarray:
    return np.array([math.nan if v is None else v * scale for v in values], dtype=float)


def _figure(ncols: int = 1, width: float = 7.0, height: float = 4.6) -> tuple[Any, Any]:
    # Figure() + Agg canvas instead of pyplot: no global backend switch, no window, thread-safe.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, ncols)
    return fig, axes


def _finish_rms_axes(ax: Any, xticks: np.ndarray, xlabel: str, title: str) -> None:
    """Labels, ticks, grid and legend of a plot of the corners' 3D RMS (mm) against xticks."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel("3D RMS error of the box corners (mm)")
    ax.set_title(title)
    ax.set_xticks(xticks)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()


def _save(fig: Any, path: Path) -> None:
    from matplotlib.ticker import AutoLocator, MaxNLocator

    for ax in fig.axes:
        if "images" in ax.get_xlabel() and isinstance(ax.xaxis.get_major_locator(), AutoLocator):
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # image counts are whole numbers
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)


def plot_fig7(d: dict, path: Path) -> None:
    fig, ax = _figure()
    x = np.array(d["images"])
    for v, values in d["rms_3d_m"].items():
        ax.plot(x, _arr(values, 1000.0), label=LABELS[v], lw=1.8, ms=5, **STYLE[v])
    _finish_rms_axes(ax, x, "number of images", "Fig. 7 — 3D RMS error (eq. 13) against the number of images")
    _save(fig, path)


def plot_fig8(d: dict, path: Path) -> None:
    fig, (left, right) = _figure(2, width=12.0)
    for v, run in d["variants"].items():
        if run.get("total_s") is None:
            continue
        st = STYLE[v]
        x = np.array(run["images"])
        cum = _arr(run["cumulative_s"])
        left.plot(x, cum, label=LABELS[v], color=st["color"], lw=1.8)
        if (run.get("finish_s") or 0.0) > 0.05 * max(run["total_s"], 1e-9):
            # The finishing step (final global BA, loop closure) only happens at the end of the
            # sequence: a vertical jump at the last count, not part of the per-insertion curve.
            left.plot([x[-1], x[-1]], [cum[-1], run["total_s"]], color=st["color"], ls=":", lw=1.8,
                      marker=st["marker"], ms=7, markevery=[1],
                      label=f"  + {run.get('finish_step') or 'finishing step'} ({run['finish_s']:.1f} s)")
        label = f"{LABELS[v]}: {_fmt(run['first_insertion_s'], '.2f')} → {_fmt(run['last_insertion_s'], '.2f')} s"
        right.plot(run["insertion_images"], _arr(run["per_insertion_s"]), label=label, lw=1.2, ms=3, **st)
    ratio = d.get("global_local_time_ratio")
    left.set_xlabel("number of images")
    left.set_ylabel("cumulative execution time (s)")
    title = "Fig. 8 — execution time against the number of images"
    if ratio:
        title += f"\n(global BA / local BA total time: {ratio:.1f}x)"
    left.set_title(title)
    left.set_ylim(bottom=0)
    left.grid(alpha=0.3)
    left.legend(fontsize=8)
    right.set_xlabel("number of images after the insertion")
    right.set_ylabel("time of the insertion (s)")
    right.set_title("time of each insertion (legend: first → last)")
    right.set_ylim(bottom=0)
    right.grid(alpha=0.3)
    right.legend(fontsize=8)
    _save(fig, path)


def plot_fig9(d: dict, path: Path) -> None:
    fig, ax = _figure()
    sig = np.array(d["sigmas"])
    variants = list(d["variants"])
    # Shift the variants a little sideways so their error bars do not hide each other.
    width = 0.06 * (sig.max() - sig.min() if len(sig) > 1 else 1.0)
    for i, v in enumerate(variants):
        r = d["variants"][v]
        dx = (i - (len(variants) - 1) / 2) * width
        st = STYLE[v]
        for j, row in enumerate(r["rms_3d_m"]):
            y = _arr(row, 1000.0)
            ax.plot(np.full(len(y), sig[j] + dx), y, ls="none", marker=".", color=st["color"], alpha=0.35, ms=5)
        ax.errorbar(sig + dx, _arr(r["mean_m"], 1000.0), yerr=_arr(r["std_m"], 1000.0), label=f"{LABELS[v]} (mean ± sd)",
                    capsize=4, lw=1.8, ms=6, **st)
    _finish_rms_axes(ax, sig, "Gaussian image noise σ (grey levels, 0–255)",
                     f"Fig. 9 — 3D RMS error against image noise\n({len(d['seeds'])} scenes per level, "
                     f"{d['images']} images; dots: single scenes)")
    _save(fig, path)


def plot_table2(d: dict, path: Path) -> None:
    fig, (left, right) = _figure(2, width=12.0)
    colors = {"box14": "tab:blue", "box18": "tab:purple", "temple": "tab:brown"}
    lines = {"local": "-", "accurate": "--"}
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in d["rows"]:
        groups.setdefault((row["sequence"], row["variant"]), []).append(row)
    for (name, v), rows in groups.items():
        if name == "box14" and ("box18", v) in groups:
            continue  # the 14-image ring is the start of the 18-image one: its curve lies under it
        x = [r["images"] for r in rows]
        end = rows[-1]
        kw = {"color": colors.get(name, "k"), "ls": lines.get(v, "-"), "marker": STYLE[v]["marker"],
              "label": f"{name}, {LABELS[v]} ({end.get('registered') or 0}/{end['images']} registered)"}
        left.plot(x, _arr([r["sparse_points"] for r in rows]), **kw)
        right.plot(x, _arr([r["rms_px"] for r in rows]), **kw)
    left.set_xlabel("number of images in the sequence")
    left.set_ylabel("sparse 3D points (log scale)")
    left.set_yscale("log")
    left.set_title("Table 2 analogue — sparse points as images are added\n(box14 = the first 14 images of box18)")
    right.set_xlabel("number of images in the sequence")
    right.set_ylabel("reprojection error, RMS over observations (px)")
    right.set_title("Table 2 analogue — reprojection error")
    right.set_ylim(bottom=0)
    for ax in (left, right):
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    _save(fig, path)


# ---------------------------------------------------------------------------------------------
# summary.md


def _fmt(value: Any, spec: str, scale: float = 1.0) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return format(value * scale, spec)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def summary_md(d: dict) -> str:
    parts = [f"# Paper bench ({'quick' if d['quick'] else 'full'} run, seed {d['seed']})\n",
             f"Run time {d['seconds']:.0f} s. Variants: "
             + "; ".join(f"**{v}** = {x['label']}" for v, x in d["variants"].items()) + ".\n"]

    f7 = d["fig7"]
    parts.append("\n## Fig. 7 — 3D RMS of the box corners (eq. 13, mm) against the number of images\n\n")
    parts.append(_table(["images"] + list(f7["rms_3d_m"]),
                        [[str(n)] + [_fmt(f7["rms_3d_m"][v][i], ".3f", 1000) for v in f7["rms_3d_m"]]
                         for i, n in enumerate(f7["images"])]))

    f8 = d["fig8"]
    n8 = f8["scene"]["n_images"]
    parts.append(f"\n## Fig. 8 — execution time ({n8}-image ring, {f8['scene']['step_deg']:g}° apart, seconds)\n\n")
    rows = []
    for v, r in f8["variants"].items():
        rows.append([v, _fmt(r.get("total_s"), ".1f"), _fmt(r.get("first_insertion_s"), ".2f"),
                     _fmt(r.get("last_insertion_s"), ".2f"), _fmt(r.get("finish_s"), ".2f"),
                     str(r.get("registered", "—"))])
    parts.append(_table(["variant", "total", "first insertion", "last insertion", "finishing step", "registered"], rows))
    parts.append(f"\nGlobal BA after every insertion / local BA, total time on {n8} images: "
                 f"**{_fmt(d['global_local_time_ratio'], '.2f')}x**.\n")

    f9 = d["fig9"]
    parts.append(f"\n## Fig. 9 — 3D RMS (mm, mean ± sd over {len(f9['seeds'])} scenes) against image noise σ\n\n")
    vs = list(f9["variants"])
    parts.append(_table(["σ (grey levels)"] + vs,
                        [[f"{s:g}"] + [f"{_fmt(f9['variants'][v]['mean_m'][i], '.3f', 1000)} ± "
                                       f"{_fmt(f9['variants'][v]['std_m'][i], '.3f', 1000)}"
                                       + ("" if f9["variants"][v]["valid"][i] == len(f9["seeds"])
                                          else f" ({f9['variants'][v]['valid'][i]} valid)")
                                       for v in vs]
                         for i, s in enumerate(f9["sigmas"])]))

    parts.append("\n## Table 2 analogue — sparse reconstruction as images are added\n\n"
                 "eq. 14 is the paper's error (sum of squared pixel errors over images × points, not rooted); "
                 "RMS is over the observations.\n\n")
    parts.append(_table(["sequence", "variant", "images", "registered", "sparse points", "eq. 14 (px²)", "RMS (px)",
                         "3D RMS (mm)"],
                        [[r["sequence"], r["variant"], str(r["images"]), str(r.get("registered", "—")),
                          str(r.get("sparse_points", "—")), _fmt(r.get("eq14"), ".4f"), _fmt(r.get("rms_px"), ".3f"),
                          _fmt(r.get("rms_3d_m"), ".3f", 1000)] for r in d["table2"]["rows"]]))

    parts.append("\n## Table 3 analogue — quasi-dense reconstruction of each sequence\n\n")
    parts.append(_table(["sequence", "variant", "images", "registered", "sparse points", "eq. 14 (px²)",
                         "dense points", "dense time (s)", "dense distance to true surface, median / 90 % (mm)"],
                        [[r["sequence"], r["variant"], str(r["images"]), str(r.get("registered", "—")),
                          str(r.get("sparse_points", "—")), _fmt(r.get("eq14"), ".4f"),
                          str(r["dense_points"]) if r.get("dense_points") is not None else "—",
                          _fmt(r.get("dense_seconds"), ".1f"),
                          f"{_fmt(r.get('dense_surface_median_m'), '.2f', 1000)} / "
                          f"{_fmt(r.get('dense_surface_p90_m'), '.2f', 1000)}"] for r in d["table3"]["rows"]]))
    failures = [r for r in d["table2"]["rows"] if r.get("failed_images") or r.get("error")]
    if failures:
        parts.append("\nImages the pipeline could not register (skipped by the pipeline):\n\n")
        for r in failures:
            what = r["error"] or ", ".join(r["failed_images"])
            parts.append(f"- {r['sequence']}, {r['variant']}, {r['images']} images: {what}\n")
    if not d["temple_found"]:
        parts.append(f"\ntempleSparseRing not found in {d['data_dir']} (set STEREOSEED_DATA): no real sequence.\n")
    return "".join(parts)


def json_clean(obj: Any) -> Any:
    """NaN and infinities become null (strict JSON has no NaN); tuples become lists."""
    if isinstance(obj, dict):
        return {str(k): json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_clean(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
