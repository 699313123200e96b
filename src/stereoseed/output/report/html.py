"""A self-contained HTML report of a reconstruction (``report.html``), for people.

One file, no network: Plotly's offline bundle is inlined once, the data of each figure is
inlined as JSON and the match image as a base64 PNG. It shows

* a summary header: registered / total images, points, reprojection RMS, mode, the model's unit,
  the run's wall time and its stages';
* an interactive 3D view of the sparse cloud (coloured), the dense cloud when the run has one
  (subsampled), and a small frustum per registered camera, the image name on hover; a scale bar
  and a distance readout (click two points) in the model's unit (:mod:`.measure`);
* the camera path seen from above (the camera centres in the ground plane of the scene);
* the reprojection error before / after bundle adjustment and the time of each insertion;
* a per-image table (status, why an image was skipped, matches, chained points, inliers,
  camera model, RMS before / after BA, time);
* the matches of the weakest insertion (the registered image with the fewest resection
  inliers against the previous registered image), a few dozen of them spread over the image.

Its title is the result folder's name (the staging folder's while the run writes it).

The report is optional: a part that cannot be built is logged and left out, and
:func:`write_report_html` itself raises only when the file cannot be written.
"""
from __future__ import annotations

import base64
import html
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.geometry.projection import camera_center
from stereoseed.io.atomic import jsonable, write_text
from stereoseed.output.report.figures import (figure_3d, figure_path, figure_reprojection, figure_times,
                             finite_cloud, insertions, finite_number, optional_part, registered_cameras, scene_frame)
from stereoseed.output.report.measure import MEASURE_SCRIPT, length_text, unit_label
from stereoseed.sfm.loop_closure import describe_loop
from stereoseed.output.result_set import result_name

__all__ = ["write_report_html", "render_report_html"]

log = logging.getLogger(__name__)
MAX_MATCH_IMAGE_WIDTH = 1280  # px
# lines drawn in the match panel: a few dozen stay apart at the panel's width; hundreds make a band
MAX_MATCH_LINES = 60


def _fmt(value: Any, digits: int = 3) -> str:
    f = finite_number(value)
    if f is None:
        return "—" if value is None else html.escape(str(value))
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    return f"{f:.{digits}f}"


def _json_for_script(data: Any) -> str:
    """JSON safe inside a <script> element (no '</script>', no HTML-significant characters)."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False, default=jsonable)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _weakest_insertion(recon: Any, report: dict[str, Any], source: Any) -> dict[str, Any] | None:
    """The registered image k >= 2 with the fewest resection inliers, matched again against the
    previous registered image j under the known geometry: a PNG (base64) and a caption."""
    from stereoseed.geometry.projection import fundamental_from_projections
    from stereoseed.output.visualize import draw_matches, spread_matches

    names = [str(v.name) for v in recon.views]
    best = None
    for r in insertions(report):
        if r.get("status") != "registered" or finite_number(r.get("resection_inliers")) is None:
            continue
        try:
            k = names.index(str(r.get("image")))
        except ValueError:
            continue
        if k < 2 or not recon.views[k].registered:
            continue
        if best is None or r["resection_inliers"] < best[1]["resection_inliers"]:
            best = (k, r)
    if best is None:
        return None
    k, row = best
    previous = recon.registered_before(k, 1)
    if not previous:
        return None
    j = previous[0]
    vj, vk = recon.views[j], recon.views[k]
    if vj.features is None or vk.features is None or source is None:
        return None
    F = fundamental_from_projections(vj.P, vk.P)
    matches = source.match(j, k, vj.restore_gray(), vk.restore_gray(), F, vj.image_size[0])
    drawn = matches.subset(spread_matches(matches, vj.features.points, vj.image_size, MAX_MATCH_LINES))
    width = vj.image_size[0] + vk.image_size[0]
    thickness = max(1, round(width / MAX_MATCH_IMAGE_WIDTH))  # a line stays a pixel wide once scaled down
    canvas = draw_matches(vj.image, vj.features.points, vk.image, vk.features.points, drawn, thickness=thickness)
    if canvas.shape[1] > MAX_MATCH_IMAGE_WIDTH:
        scale = MAX_MATCH_IMAGE_WIDTH / canvas.shape[1]
        canvas = cv2.resize(canvas, (MAX_MATCH_IMAGE_WIDTH, max(1, round(canvas.shape[0] * scale))),
                            interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:
        raise ValueError("PNG encoding failed")
    turned = [v.name for v in (vj, vk) if getattr(v, "rotated_180", False)]
    shown = (f"all {len(matches)} matches under the known epipolar geometry drawn" if len(drawn) == len(matches) else
             f"{len(drawn)} of the {len(matches)} matches under the known epipolar geometry drawn, spread over the "
             f"image (the best of each part first)")
    caption = (f"{vj.name} (left) and {vk.name} (right), the weakest insertion: {row['resection_inliers']} resection "
               f"inliers; {shown}; red (lowest ZNCC) to green (highest).")
    if turned:
        caption += f" Drawn as the run used them: {', '.join(turned)} turned by 180°."
    return {"png": base64.b64encode(png.tobytes()).decode("ascii"), "caption": caption,
            "width": int(canvas.shape[1]), "height": int(canvas.shape[0])}


# ---------------------------------------------------------------- HTML parts
def _summary(dense_cloud: Any, report: dict[str, Any]) -> str:
    rep = report.get("reprojection") if isinstance(report.get("reprojection"), dict) else {}
    items = [("registered", f"{_fmt(report.get('registered'))} / {_fmt(report.get('images'))} images"),
             ("sparse points", _points_text(report)),
             ("reprojection RMS", f"{_fmt(rep.get('rms_px'))} px" if finite_number(rep.get("rms_px")) is not None else "—"),
             ("observations", _fmt(rep.get("observations"))),
             ("mode", html.escape(str(report.get("mode", "—")))),
             ("camera model", _model_text(report)),
             ("BA", html.escape(f"{report.get('ba', '—')}" + (f", window {report['window']}" if report.get("window") else ""))),
             ("unit", html.escape(report["unit"]) if report.get("unit") else "the calibration's (not named)")]
    dense = report.get("dense") if isinstance(report.get("dense"), dict) else None
    n_dense = (dense or {}).get("points")
    if n_dense is None and dense_cloud is not None:
        n_dense = len(dense_cloud)
    if n_dense is not None:
        items.insert(2, ("dense points", _fmt(n_dense)))
    items += _times(report, dense)
    loop = (report.get("final") or {}).get("loop_closure") if isinstance(report.get("final"), dict) else None
    if isinstance(loop, dict):
        items.append(("loop closure", _loop_text(loop, report.get("unit") if isinstance(report.get("unit"), str) else None)))
    return "".join(f'<div class="kv"><span>{html.escape(k)}</span><b>{v}</b></div>' for k, v in items)


def _model_text(report: dict[str, Any]) -> str:
    """The camera model asked for, and what the run used when no image zoomed (every row then
    says "fixed": the calibrated intrinsics kept)."""
    asked = html.escape(str(report.get("camera_model", "—")))
    final = report.get("final") if isinstance(report.get("final"), dict) else {}
    if final.get("no_zoom") and asked not in ("fixed", "—"):
        return f"fixed: no image zoomed ({asked} asked)"
    return asked


def _points_text(report: dict[str, Any]) -> str:
    """The sparse points written (report "exported_points"), and the far ones left out."""
    far = finite_number(report.get("far_points_dropped"))
    text = _fmt(report.get("exported_points", report.get("points")))
    return text + (f" ({int(far)} far left out)" if far else "")


def _loop_text(loop: dict[str, Any], unit: str | None) -> str:
    """The loop closure's verdict and gap (HTML): "not closed" in bold only when the gap is beyond
    what the cameras measure (a real failure); the other verdicts say what the run could not show."""
    try:
        text = describe_loop(loop, lambda x: length_text(x, unit))
    except (KeyError, TypeError, ValueError):  # a report.json edited or from another version
        text = "closed" if loop.get("closed") else f"not closed ({loop.get('reason', '')})"
    verdict = loop.get("verdict", "closed" if loop.get("closed") else "not closed")
    return html.escape(text) if verdict == "not closed" else f'<span style="font-weight:normal">{html.escape(text)}</span>'


def _times(report: dict[str, Any], dense: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The run's wall time and its stages' (report "timing", written by the whole run) or, for a
    report without it, the stages the report holds and their sum."""
    timing = report.get("timing") if isinstance(report.get("timing"), dict) else {}
    stages = timing.get("stages_s") if isinstance(timing.get("stages_s"), dict) else {}
    stages = {str(k): finite_number(v) for k, v in stages.items() if finite_number(v) is not None}
    total = finite_number(timing.get("total_s"))
    label = "total time (this command; resumed)" if report.get("resumed_images") else "total time"
    if total is None:  # the incremental run's and the dense stage's times, as the report holds them
        stages = {k: v for k, v in (("sparse", finite_number(report.get("seconds"))),
                                    ("dense", finite_number((dense or {}).get("seconds")))) if v is not None}
        total, label = (sum(stages.values()), "total time (sparse + dense)") if stages else (None, label)
    if total is None:
        return [("total time", "—")]
    parts = " · ".join(f"{html.escape(k)} {v:.1f} s" for k, v in stages.items())
    return [(label, f"{total:.1f} s")] + ([("stages", parts)] if parts else [])


def _columns(unit: str | None) -> tuple[str, ...]:
    return ("#", "image", "status", "reason / registered by", "matches", "chained points", "inliers",
            "camera model", "RMS before BA (px)", "RMS after BA (px)", "new points", "time (s)",
            f"position σ ({unit_label(unit)})", "trust")


def _trust_cells(judged: dict[str, Any] | None) -> list[str]:
    """The per-image table's uncertainty (the worst axis of the 1-sigma position) and trust cells."""
    if judged is None:
        return ["—", ""]
    u = judged.get("uncertainty") if isinstance(judged.get("uncertainty"), dict) else {}
    sigmas = [s for s in (u.get("position_sigma") or []) if finite_number(s) is not None]
    sigma = f"{max(sigmas):.3g}" if sigmas else ("undetermined" if u else "—")
    if judged.get("reliable") is False:
        return [html.escape(sigma), f'flagged: {html.escape(str(judged.get("flag_reason") or ""))}']
    return [html.escape(sigma), "reliable"]


def _table(recon: Any, report: dict[str, Any]) -> str:
    rows = []
    models = {str(v.name): getattr(v, "camera_model", None) for v in getattr(recon, "views", [])}
    final = report.get("final") if isinstance(report.get("final"), dict) else {}
    trust = (final.get("trust") or {}).get("cameras") or {} if isinstance(final.get("trust"), dict) else {}
    for n, r in enumerate(insertions(report)):
        status = str(r.get("status", "—"))
        ba = r.get("ba") if isinstance(r.get("ba"), dict) else {}
        seconds = r.get("seconds") if isinstance(r.get("seconds"), dict) else {}
        reason = r.get("reason") if status == "failed" else r.get("registered_by")
        model = r.get("resection_model") or models.get(str(r.get("image"))) or (
            "calibrated" if status.startswith("calibrated") else None)
        if ba.get("skipped"):
            before = after = "skipped"
        else:
            before, after = _fmt(ba.get("rms_before_px")), _fmt(ba.get("rms_after_px"))
        cls = "failed" if status == "failed" else "pair" if status.startswith("calibrated") else ""
        cells = [str(n), html.escape(str(r.get("image", "?"))), html.escape(status),
                 html.escape(str(reason)) if reason else "", _fmt(r.get("matches")), _fmt(r.get("chained_points")),
                 _fmt(r.get("resection_inliers")), html.escape(str(model)) if model else "—", before, after,
                 _fmt(r.get("new_points")), _fmt(seconds.get("total"), 2)]
        judged = trust.get(str(r.get("image"))) if isinstance(trust, dict) else None
        cells += _trust_cells(judged if isinstance(judged, dict) else None)
        if isinstance(judged, dict) and judged.get("reliable") is False:
            cls = cls or "flagged"
        tds = "".join(f"<td>{c}</td>" for c in cells)
        rows.append(f'<tr class="{cls}" data-status="{html.escape(status)}">{tds}</tr>')
    head = "".join(f"<th>{html.escape(c)}</th>" for c in _columns(report.get("unit")))
    return f'<table id="per-image"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;background:#f5f6f8;color:#1d2330}
header{background:#1f2430;color:#fff;padding:14px 24px}
header h1{margin:0 0 8px;font-size:20px;font-weight:600}
.summary{display:flex;flex-wrap:wrap;gap:6px 22px}
.kv span{color:#9aa3b5;margin-right:6px;font-size:13px}.kv b{font-weight:600}
main{padding:14px 24px}
section{background:#fff;border-radius:6px;box-shadow:0 1px 3px rgba(0,0,0,.12);margin:0 0 16px;padding:10px 14px}
section h2{font-size:16px;margin:4px 0 8px}
.grid{display:grid;grid-template-columns:repeat(auto-fit,minmax(340px,1fr));gap:16px}
.plot{width:100%;height:360px}#view3d{height:600px}
.note{color:#667;font-size:13px}
table{border-collapse:collapse;font-size:13px;width:100%}
th,td{border-bottom:1px solid #e3e6ec;padding:4px 6px;text-align:right;white-space:nowrap}
th{white-space:normal;vertical-align:bottom}
th:nth-child(2),td:nth-child(2),th:nth-child(3),td:nth-child(3),th:nth-child(4),td:nth-child(4),
th:nth-child(8),td:nth-child(8){text-align:left}
td:nth-child(4){white-space:normal;max-width:420px}
tr.failed td{background:#fde8e8;color:#8a1c1c}tr.pair td{background:#fff4e5}tr.flagged td{background:#fff1cc}
td:nth-child(14){white-space:normal;max-width:360px;text-align:left}
.table-wrap{overflow-x:auto}
img.matches{max-width:100%;height:auto;border:1px solid #ccd}
"""

_SCRIPT = """
(function(){
  var figures = JSON.parse(document.getElementById('figures').textContent);
  var config = {displaylogo: false, responsive: true};
  function webgl(){
    try { var c = document.createElement('canvas');
          return !!(window.WebGLRenderingContext && (c.getContext('webgl') || c.getContext('experimental-webgl'))); }
    catch (e) { return false; }
  }
  var hasWebGL = webgl();
  Object.keys(figures).forEach(function(id){
    var el = document.getElementById(id), fig = figures[id];
    if (!el) return;
    if (fig.webgl && !hasWebGL) {
      el.className += ' note';
      el.style.height = 'auto';
      el.textContent = 'This browser has no WebGL: the 3D view cannot be drawn (the other parts of the report can).';
      return;
    }
    Plotly.newPlot(el, fig.data, fig.layout, config);
    if (fig.measure) stereoseedMeasure(el, fig.measure);
  });
  document.body.setAttribute('data-rendered', 'true');
})();
"""


def render_report_html(recon: Any, report: dict[str, Any], title: str | None = None, dense: Any = None,
                       source: Any = None, mesh: Any = None) -> str:
    """The report's HTML text (see :func:`write_report_html`); optional parts that fail are
    logged and left out."""
    report = report if isinstance(report, dict) else {}
    sparse = optional_part("the sparse cloud", lambda: finite_cloud(*recon.live_points()))
    if sparse is None:
        sparse = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    cams = optional_part("the cameras", lambda: registered_cameras(recon)) or []
    frame = optional_part("the scene frame", lambda: scene_frame(sparse[0], np.array([camera_center(P) for _, _, P, _ in cams]).reshape(-1, 3)))
    figures: dict[str, Any] = {}
    unit = report.get("unit") if isinstance(report.get("unit"), str) else None
    if frame is not None:
        rig = getattr(recon, "rig", None) is not None
        fig = optional_part("the 3D view", lambda: figure_3d(dense, frame, sparse, cams, unit, mesh, rig))
        if fig is not None and fig["data"]:
            figures["view3d"] = {**fig, "webgl": True}
        fig = optional_part("the camera path", lambda: figure_path(frame, sparse[0], cams, unit))
        if fig is not None and fig["data"]:
            figures["path"] = fig
    for key, what, build in (("reprojection", "the reprojection plot", figure_reprojection),
                             ("times", "the time plot", figure_times)):
        fig = optional_part(what, lambda: build(report))
        if fig is not None:
            figures[key] = fig
    matches = optional_part("the weakest insertion's matches", lambda: _weakest_insertion(recon, report, source))
    summary = optional_part("the summary", lambda: _summary(dense, report)) or ""
    table = optional_part("the per-image table", lambda: _table(recon, report)) or '<p class="note">no per-image report</p>'
    encoded = {key: optional_part(f"figure {key!r}", lambda: _json_for_script(fig)) for key, fig in figures.items()}
    figures = {key: fig for key, fig in figures.items() if encoded[key] is not None}
    plotly_js = optional_part("the Plotly bundle", _plotly_js) if figures else None
    if plotly_js is None:
        figures = {}

    def plot_section(key: str, heading: str, note: str = "", after: str = "") -> str:
        if key not in figures:
            return ""
        extra = f'<p class="note">{note}</p>' if note else ""
        return f'<section><h2>{heading}</h2>{extra}<div id="{key}" class="plot"></div>{after}</section>'

    title = title or "stereoseed reconstruction"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f'<header><h1>{html.escape(title)}</h1><div class="summary">{summary}</div></header><main>',
        plot_section("view3d", "3D view",
                     "Sparse cloud (coloured), dense cloud when computed (subsampled), and a frustum per registered "
                     "camera (orange: the calibrated pair; the tick marks the top of the image); the yellow scale bar "
                     f"and the coordinates are in {html.escape(unit or 'the calibration’s unit')}. Drag to rotate, "
                     "scroll to zoom, hover a frustum for its image; click a legend entry to hide it; click two points "
                     "to measure their distance.",
                     '<p id="distance" class="note">distance: click two points of the view</p>'),
        '<div class="grid">',
        plot_section("path", "Camera path seen from above",
                     "Camera centres in the ground plane of the scene, in sequence order, with their viewing "
                     "directions, over the sparse points."),
        plot_section("reprojection", "Reprojection error before / after bundle adjustment"),
        plot_section("times", "Time per insertion"),
        "</div>",
        f'<section><h2>Per image</h2><div class="table-wrap">{table}</div></section>',
    ]
    if matches is not None:
        parts.append(f'<section><h2>Matches of the weakest insertion</h2><p class="note">{html.escape(matches["caption"])}'
                     f'</p><img class="matches" alt="matches of the weakest insertion" width="{matches["width"]}" '
                     f'height="{matches["height"]}" src="data:image/png;base64,{matches["png"]}"></section>')
    parts.append("</main>")
    if figures:
        figures_json = "{" + ",".join(f"{json.dumps(key)}:{encoded[key]}" for key in figures) + "}"
        parts.append(f'<script type="application/json" id="figures">{figures_json}</script>')
        parts.append(f"<script>{plotly_js}</script>")
        parts.append(f"<script>{MEASURE_SCRIPT}{_SCRIPT}</script>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _plotly_js() -> str:
    from plotly.offline import get_plotlyjs

    return get_plotlyjs()


def write_report_html(recon: Any, report: dict[str, Any], out_dir: str | Path, dense: Any = None,
                      source: Any = None, mesh: Any = None) -> Path:
    """Write ``out_dir/report.html``, one self-contained file (no network), atomically (a
    temporary file in out_dir replaces it), titled by the result folder's name (:func:`stereoseed.output.result_set.result_name`).
    Returns its path.

    recon: the :class:`~stereoseed.scene.reconstruction.Reconstruction`; report: the run's report
    dict (report.json); dense: the :class:`~stereoseed.dense.densify.DenseCloud`, shown when given;
    source: a correspondence source (``match``) to draw the weakest insertion's matches with;
    mesh: the dense cloud's :class:`~stereoseed.dense.mesh.Mesh`, shown when given.
    A part that cannot be built is logged and left out; only an error writing the file raises.
    """
    path = Path(out_dir) / "report.html"
    text = render_report_html(recon, report, title=f"{result_name(path.parent)} — stereoseed reconstruction",
                              dense=dense, source=source, mesh=mesh)
    write_text(path, text)
    log.info("wrote %s (%.1f MB)", path, len(text) / 1e6)
    return path
