"""A self-contained HTML report of a reconstruction (``report.html``), for people.

One file, no network: Plotly's offline bundle is inlined once, the data of each figure is
inlined as JSON and the match image as a base64 PNG. It shows

* a summary header: registered / total images, points, reprojection RMS, mode, total time;
* an interactive 3D view of the sparse cloud (coloured), the dense cloud when the run has one
  (subsampled), and a small frustum per registered camera, the image name on hover;
* the camera path seen from above (the camera centres in the ground plane of the scene);
* the reprojection error before / after bundle adjustment and the time of each insertion;
* a per-image table (status, why an image was skipped, matches, chained points, inliers,
  camera model, RMS before / after BA, time);
* the matches of the weakest insertion (the registered image with the fewest resection
  inliers against the previous registered image).

The report is optional: a part that cannot be built is logged and left out, and
:func:`write_report_html` itself raises only when the file cannot be written.
"""
from __future__ import annotations

import base64
import html
import json
import logging
import math
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from .io import atomic_path

__all__ = ["write_report_html", "render_report_html"]

log = logging.getLogger(__name__)

MAX_DENSE_POINTS = 50_000  # the dense cloud is subsampled to this many points
MAX_SPARSE_POINTS = 50_000
MAX_MATCH_IMAGE_WIDTH = 1280  # px
FRUSTUM_DEPTH = 0.07  # frustum depth as a fraction of the scene size
_TIME_PARTS = ("features", "matching", "resection", "triangulation", "bundle")


# ---------------------------------------------------------------- small helpers
def _optional(what: str, build: Callable[[], Any]) -> Any:
    """build(), or None (logged) when it fails: no part of the report may fail the run."""
    try:
        return build()
    except Exception as e:  # noqa: BLE001 - the report is optional, the reconstruction is not
        log.warning("report.html: %s left out (%s: %s)", what, type(e).__name__, e)
        log.debug("report.html: %s", what, exc_info=True)
        return None


def _num(value: Any) -> float | None:
    """A finite float, or None."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _fmt(value: Any, digits: int = 3) -> str:
    f = _num(value)
    if f is None:
        return "—" if value is None else html.escape(str(value))
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    return f"{f:.{digits}f}"


def _json_for_script(data: Any) -> str:
    """JSON safe inside a <script> element (no '</script>', no HTML-significant characters)."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False, default=_jsonable)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _rounded(a: np.ndarray, scale: float) -> list:
    """Coordinates rounded to 1e-5 of the scene size (keeps the file small)."""
    if scale > 0:
        decimals = int(np.clip(5 - math.floor(math.log10(scale)), 0, 12))
    else:
        decimals = 6
    return np.round(np.asarray(a, np.float64), decimals).tolist()


def _hex_colors(colors: np.ndarray) -> list[str]:
    c = np.clip(np.asarray(colors), 0, 255).astype(np.uint8).reshape(-1, 3)
    return ["#%02x%02x%02x" % tuple(row) for row in c]


def _subsample(points: np.ndarray, colors: np.ndarray, limit: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """At most ``limit`` points, a reproducible random subset."""
    if len(points) <= limit:
        return points, colors
    keep = np.sort(np.random.default_rng(seed).choice(len(points), limit, replace=False))
    return points[keep], colors[keep]


def _finite_cloud(points: Any, colors: Any) -> tuple[np.ndarray, np.ndarray]:
    if points is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    cols = (np.full((len(pts), 3), 128, np.uint8) if colors is None or len(colors) != len(pts)
            else np.asarray(colors).reshape(-1, 3))
    ok = np.all(np.isfinite(pts), axis=1)
    return pts[ok], cols[ok]


# ---------------------------------------------------------------- geometry
def _registered_cameras(recon: Any) -> list[tuple[int, str, np.ndarray, tuple[int, int]]]:
    """(index, name, P_input, (width, height)) of each registered view with a finite camera."""
    cams = []
    for i, v in enumerate(recon.views):
        try:
            P = v.P_input
            if P is None or not np.all(np.isfinite(P)) or abs(np.linalg.det(P[:, :3])) < 1e-300:
                continue
            cams.append((i, str(v.name), np.asarray(P, np.float64), tuple(v.image_size)))
        except Exception as e:  # noqa: BLE001
            log.debug("report.html: view %d has no usable camera (%s)", i, e)
    return cams


def _center(P: np.ndarray) -> np.ndarray:
    return -np.linalg.solve(P[:, :3], P[:, 3])


def _backproject(P: np.ndarray, pixels: np.ndarray, depth: float) -> np.ndarray:
    """World points (N, 3) at camera depth ``depth`` on the rays of pixels (N, 2), for any sign
    and scale of P (depth as in Hartley & Zisserman eq. 6.15)."""
    M = P[:, :3]
    rays = np.linalg.solve(M, np.column_stack([pixels, np.ones(len(pixels))]).T).T  # M @ ray = (u, v, 1)
    t = depth * np.linalg.norm(M[2]) * np.sign(np.linalg.det(M))
    return _center(P) + t * rays


def _viewing_direction(P: np.ndarray) -> np.ndarray:
    M = P[:, :3]
    d = np.sign(np.linalg.det(M)) * M[2]
    return d / np.linalg.norm(d)


def _scene_frame(points: np.ndarray, centers: np.ndarray) -> dict[str, Any]:
    """Size of the scene and its ground plane: 'up' is the normal of the plane the camera
    centres lie in (a ring around the object), pointing from the object to the cameras; with
    fewer than three cameras or a straight path, +Z. Returns size, centre, up, the two ground
    axes and their labels (X / Y when the plane is a coordinate plane)."""
    both = np.vstack([p for p in (points, centers) if len(p)]) if (len(points) or len(centers)) else np.zeros((1, 3))
    if len(points) >= 10:  # robust to a few stray points
        lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    else:
        lo, hi = both.min(0), both.max(0)
    if len(centers):
        lo, hi = np.minimum(lo, centers.min(0)), np.maximum(hi, centers.max(0))
    size = float(np.linalg.norm(hi - lo)) or 1.0
    target = np.median(points, axis=0) if len(points) else both.mean(0)
    up = np.array([0.0, 0.0, 1.0])
    if len(centers) >= 3:
        c = centers - centers.mean(0)
        _, s, vt = np.linalg.svd(c, full_matrices=False)
        if s[1] > 1e-6 * max(s[0], 1e-300):  # not on one line
            up = vt[2] / np.linalg.norm(vt[2])
            if np.dot(centers.mean(0) - target, up) < 0:
                up = -up
    axis = int(np.argmax(np.abs(up)))
    if abs(up[axis]) > 0.9:  # a coordinate plane: show it in the coordinates
        others = [a for a in range(3) if a != axis]
        e1, e2 = np.eye(3)[others[0]], np.eye(3)[others[1]]
        names = "XYZ"
        labels = (names[others[0]], names[others[1]])
    else:
        e1 = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(up, e1)
        labels = ("ground axis 1", "ground axis 2")
    return {"size": size, "target": target, "up": up, "e1": e1, "e2": e2, "labels": labels, "lo": lo, "hi": hi}


def _near(points: np.ndarray, frame: dict[str, Any]) -> np.ndarray:
    """(N,) bool: the point lies within half a scene size of the scene's robust bounding box (a
    few far outliers would otherwise shrink the scene to a dot in the 3D view)."""
    margin = 0.5 * frame["size"]
    return np.all((points >= frame["lo"] - margin) & (points <= frame["hi"] + margin), axis=1)


def _shown(points: np.ndarray, colors: np.ndarray, frame: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, str]:
    """The points near the scene, and a note of how many far ones are not shown."""
    near = _near(points, frame)
    far = int(len(points) - near.sum())
    return points[near], colors[near], (f"; {far} far outlier{'s' if far > 1 else ''} not shown" if far else "")


# ---------------------------------------------------------------- figures (Plotly JSON)
_DARK = "#1f2430"


def _figure_3d(recon: Any, frame: dict[str, Any], sparse: tuple[np.ndarray, np.ndarray],
               cams: list[tuple[int, str, np.ndarray, tuple[int, int]]]) -> dict[str, Any]:
    size = frame["size"]
    data: list[dict[str, Any]] = []
    dense = _optional("the dense cloud", lambda: _finite_cloud(getattr(recon, "dense_points", None),
                                                                getattr(recon, "dense_colors", None)))
    if dense is not None and len(dense[0]):
        near_pts, near_cols, far = _shown(*dense, frame)
        pts, cols = _subsample(near_pts, near_cols, MAX_DENSE_POINTS)
        n_all = len(dense[0])
        data.append({"type": "scatter3d", "mode": "markers", "name": f"dense ({len(pts)} of {n_all} points{far})",
                     "x": _rounded(pts[:, 0], size), "y": _rounded(pts[:, 1], size), "z": _rounded(pts[:, 2], size),
                     "marker": {"size": 1.2, "color": _hex_colors(cols)}, "hoverinfo": "skip"})
    near_pts, near_cols, far = _shown(*sparse, frame)
    pts, cols = _subsample(near_pts, near_cols, MAX_SPARSE_POINTS)
    if len(pts):
        data.append({"type": "scatter3d", "mode": "markers", "name": f"sparse ({len(sparse[0])} points{far})",
                     "x": _rounded(pts[:, 0], size), "y": _rounded(pts[:, 1], size), "z": _rounded(pts[:, 2], size),
                     "marker": {"size": 2.0 if dense is None or not len(dense[0]) else 1.5, "color": _hex_colors(cols)},
                     "hoverinfo": "skip"})
    depth = FRUSTUM_DEPTH * size
    groups: dict[str, list] = {"calibrated pair": [], "registered": []}
    for i, name, P, (w, h) in cams:
        corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])
        c = _center(P)
        q = _backproject(P, corners, depth)
        top = _backproject(P, np.array([[(w - 1) / 2.0, -0.25 * h]]), depth)[0]  # the 'up' tick above the image
        segments = [(c, q[0]), (c, q[1]), (c, q[2]), (c, q[3]), (q[0], q[1]), (q[1], q[2]), (q[2], q[3]),
                    (q[3], q[0]), (q[0], top), (top, q[1])]
        groups["calibrated pair" if i < 2 else "registered"].append((i, name, segments))
    colours = {"calibrated pair": "#ff7f0e", "registered": "#d62728"}
    for group, items in groups.items():
        if not items:
            continue
        xyz: list[list] = [[], [], []]
        texts: list = []
        for i, name, segments in items:
            for a, b in segments:
                for d in range(3):
                    xyz[d] += [float(a[d]), float(b[d]), None]
                texts += [f"{i}: {name}"] * 2 + [None]
        rounded = [[None if v is None else round(v, 7) for v in col] for col in xyz]
        data.append({"type": "scatter3d", "mode": "lines", "name": f"cameras: {group}", "x": rounded[0],
                     "y": rounded[1], "z": rounded[2], "text": texts, "line": {"color": colours[group], "width": 3},
                     "hovertemplate": "%{text}<extra></extra>"})
    if cams:
        centres = np.array([_center(P) for _, _, P, _ in cams])
        data.append({"type": "scatter3d", "mode": "markers", "name": "camera centres", "showlegend": False,
                     "x": _rounded(centres[:, 0], size), "y": _rounded(centres[:, 1], size),
                     "z": _rounded(centres[:, 2], size), "text": [f"{i}: {n}" for i, n, _, _ in cams],
                     "marker": {"size": 3, "color": "#ffffff", "line": {"color": "#d62728", "width": 1}},
                     "hovertemplate": "%{text}<extra></extra>"})
    up = frame["up"]
    # look from outside the ring, slightly above it, at the scene's centre
    side = frame["e1"] * 0.9 + frame["e2"] * 0.9
    eye = side + up * 0.9
    layout = {
        "margin": {"l": 0, "r": 0, "t": 0, "b": 0}, "paper_bgcolor": _DARK, "font": {"color": "#e6e6e6"},
        "legend": {"x": 0.01, "y": 0.99, "bgcolor": "rgba(0,0,0,0.35)"},
        "scene": {"aspectmode": "data", "bgcolor": _DARK,
                  "xaxis": {"title": {"text": "X"}, "color": "#9aa3b5", "gridcolor": "#394050"},
                  "yaxis": {"title": {"text": "Y"}, "color": "#9aa3b5", "gridcolor": "#394050"},
                  "zaxis": {"title": {"text": "Z"}, "color": "#9aa3b5", "gridcolor": "#394050"},
                  "camera": {"up": dict(zip("xyz", map(float, up))), "eye": dict(zip("xyz", map(float, eye))),
                             "center": {"x": 0, "y": 0, "z": 0}}},
        "uirevision": "keep",
    }
    return {"data": data, "layout": layout}


def _figure_path(frame: dict[str, Any], sparse: np.ndarray,
                 cams: list[tuple[int, str, np.ndarray, tuple[int, int]]]) -> dict[str, Any]:
    e1, e2 = frame["e1"], frame["e2"]
    data: list[dict[str, Any]] = []
    sparse = sparse[_near(sparse, frame)]
    if len(sparse):
        # SVG, not WebGL: the path stays drawn in a browser without WebGL; a subset suffices as a backdrop
        pts = sparse if len(sparse) <= 4000 else sparse[np.random.default_rng(0).choice(len(sparse), 4000, False)]
        data.append({"type": "scatter", "mode": "markers", "name": "sparse points",
                     "x": np.round(pts @ e1, 5).tolist(), "y": np.round(pts @ e2, 5).tolist(),
                     "marker": {"size": 2, "color": "rgba(120,120,120,0.35)"}, "hoverinfo": "skip"})
    if cams:
        c = np.array([_center(P) for _, _, P, _ in cams])
        d = np.array([_viewing_direction(P) for _, _, P, _ in cams])
        u, v = c @ e1, c @ e2
        length = 0.08 * frame["size"]
        du, dv = d @ e1, d @ e2
        norm = np.hypot(du, dv)
        norm[norm == 0] = 1.0
        ax, ay = [], []
        for k in range(len(c)):
            ax += [u[k], u[k] + length * du[k] / norm[k], None]
            ay += [v[k], v[k] + length * dv[k] / norm[k], None]
        data.append({"type": "scatter", "mode": "lines", "name": "viewing direction", "x": ax, "y": ay,
                     "line": {"color": "#1f77b4", "width": 1.5}, "hoverinfo": "skip"})
        names = [f"{i}: {n}" for i, n, _, _ in cams]
        data.append({"type": "scatter", "mode": "lines+markers+text", "name": "camera centres (in order)",
                     "x": np.round(u, 6).tolist(), "y": np.round(v, 6).tolist(), "text": [str(i) for i, _, _, _ in cams],
                     "textposition": "top center", "customdata": names, "hovertemplate": "%{customdata}<extra></extra>",
                     "marker": {"size": 8, "color": ["#ff7f0e" if i < 2 else "#d62728" for i, _, _, _ in cams]},
                     "line": {"color": "#d62728", "width": 1, "dash": "dot"}})
    labels = frame["labels"]
    layout = {"margin": {"l": 50, "r": 10, "t": 10, "b": 40}, "showlegend": False,
              "xaxis": {"title": {"text": labels[0]}, "zeroline": False},
              "yaxis": {"title": {"text": labels[1]}, "zeroline": False, "scaleanchor": "x", "scaleratio": 1}}
    return {"data": data, "layout": layout}


def _insertions(report: dict[str, Any]) -> list[dict[str, Any]]:
    return [r for r in report.get("per_image") or [] if isinstance(r, dict)]


def _figure_reprojection(report: dict[str, Any]) -> dict[str, Any] | None:
    names, before, after = [], [], []
    for r in _insertions(report):
        ba = r.get("ba") if isinstance(r.get("ba"), dict) else {}
        b, a = _num(ba.get("rms_before_px")), _num(ba.get("rms_after_px"))
        if b is None and a is None:
            continue
        names.append(str(r.get("image", "?")))
        before.append(b)
        after.append(a)
    final = (report.get("final") or {}).get("final_ba") if isinstance(report.get("final"), dict) else None
    if isinstance(final, dict) and (_num(final.get("rms_before_px")) is not None):
        names.append("final BA")
        before.append(_num(final.get("rms_before_px")))
        after.append(_num(final.get("rms_after_px")))
    if not names:
        return None
    data = [{"type": "bar", "name": "before BA", "x": names, "y": before, "marker": {"color": "#ff7f0e"}},
            {"type": "bar", "name": "after BA", "x": names, "y": after, "marker": {"color": "#2ca02c"}}]
    layout = {"barmode": "group", "margin": {"l": 55, "r": 10, "t": 10, "b": 90},
              "yaxis": {"title": {"text": "reprojection RMS (px)"}, "rangemode": "tozero"},
              "xaxis": {"type": "category", "tickangle": -45}, "legend": {"orientation": "h", "y": 1.1}}
    return {"data": data, "layout": layout}


def _figure_times(report: dict[str, Any]) -> dict[str, Any] | None:
    rows = [r for r in _insertions(report) if isinstance(r.get("seconds"), dict)]
    if not rows:
        return None
    names = [str(r.get("image", "?")) for r in rows]
    data = []
    for part in _TIME_PARTS + ("other",):
        ys = []
        for r in rows:
            s = r["seconds"]
            if part == "other":
                total = _num(s.get("total"))
                known = sum(_num(s.get(p)) or 0.0 for p in _TIME_PARTS)
                ys.append(max(0.0, total - known) if total is not None else None)
            else:
                ys.append(_num(s.get(part)))
        if any(y for y in ys):
            data.append({"type": "bar", "name": part, "x": names, "y": ys})
    layout = {"barmode": "stack", "margin": {"l": 55, "r": 10, "t": 10, "b": 90},
              "yaxis": {"title": {"text": "seconds"}, "rangemode": "tozero"},
              "xaxis": {"type": "category", "tickangle": -45}, "legend": {"orientation": "h", "y": 1.1}}
    return {"data": data, "layout": layout}


# ---------------------------------------------------------------- the weakest insertion's matches
def _weakest_insertion(recon: Any, report: dict[str, Any]) -> dict[str, Any] | None:
    """The registered image k >= 2 with the fewest resection inliers, matched again against the
    previous registered image j under the known geometry: a PNG (base64) and a caption."""
    from .camera import fundamental_from_projections
    from .visualize import draw_matches

    names = [str(v.name) for v in recon.views]
    best = None
    for r in _insertions(report):
        if r.get("status") != "registered" or _num(r.get("resection_inliers")) is None:
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
    previous = [j for j in range(k) if recon.views[j].registered]
    if not previous:
        return None
    j = previous[-1]
    vj, vk = recon.views[j], recon.views[k]
    if vj.features is None or vk.features is None or recon.source is None:
        return None
    F = fundamental_from_projections(vj.P, vk.P)
    matches = recon.source.match(j, k, vj.features, vk.features, F, vj.image.shape[1])
    canvas = draw_matches(vj.image, vj.features.points, vk.image, vk.features.points, matches)
    if canvas.shape[1] > MAX_MATCH_IMAGE_WIDTH:
        scale = MAX_MATCH_IMAGE_WIDTH / canvas.shape[1]
        canvas = cv2.resize(canvas, (MAX_MATCH_IMAGE_WIDTH, max(1, round(canvas.shape[0] * scale))),
                            interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:
        raise ValueError("PNG encoding failed")
    turned = [v.name for v in (vj, vk) if getattr(v, "rotated_180", False)]
    caption = (f"{vj.name} (left) and {vk.name} (right), the weakest insertion: {row['resection_inliers']} resection "
               f"inliers; {len(matches)} matches under the known epipolar geometry, red (lowest ZNCC) to green "
               f"(highest).")
    if turned:
        caption += f" Drawn as the run used them: {', '.join(turned)} turned by 180°."
    return {"png": base64.b64encode(png.tobytes()).decode("ascii"), "caption": caption,
            "width": int(canvas.shape[1]), "height": int(canvas.shape[0])}


# ---------------------------------------------------------------- HTML parts
def _summary(recon: Any, report: dict[str, Any]) -> str:
    rep = report.get("reprojection") if isinstance(report.get("reprojection"), dict) else {}
    items = [("registered", f"{_fmt(report.get('registered'))} / {_fmt(report.get('images'))} images"),
             ("sparse points", _fmt(report.get("points"))),
             ("reprojection RMS", f"{_fmt(rep.get('rms_px'))} px" if _num(rep.get("rms_px")) is not None else "—"),
             ("observations", _fmt(rep.get("observations"))),
             ("mode", html.escape(str(report.get("mode", "—")))),
             ("camera model", html.escape(str(report.get("camera_model", "—")))),
             ("BA", html.escape(f"{report.get('ba', '—')}" + (f", window {report['window']}" if report.get("window") else ""))),
             ("total time", f"{_fmt(report.get('seconds'), 1)} s" if _num(report.get("seconds")) is not None else "—")]
    dense = report.get("dense") if isinstance(report.get("dense"), dict) else None
    n_dense = (dense or {}).get("points")
    if n_dense is None and getattr(recon, "dense_points", None) is not None:
        n_dense = len(recon.dense_points)
    if n_dense is not None:
        items.insert(2, ("dense points", _fmt(n_dense)))
    if dense and _num(dense.get("seconds")) is not None:
        items.append(("dense stage", f"{_fmt(dense.get('seconds'), 1)} s"))
    loop = (report.get("final") or {}).get("loop_closure") if isinstance(report.get("final"), dict) else None
    if isinstance(loop, dict):
        items.append(("loop closure", "closed" if loop.get("closed") else html.escape(f"not closed ({loop.get('reason', '')})")))
    return "".join(f'<div class="kv"><span>{html.escape(k)}</span><b>{v}</b></div>' for k, v in items)


_COLUMNS = ("#", "image", "status", "reason / registered by", "matches", "chained points", "inliers",
            "camera model", "RMS before BA (px)", "RMS after BA (px)", "new points", "time (s)")


def _table(recon: Any, report: dict[str, Any]) -> str:
    rows = []
    models = {str(v.name): getattr(v, "camera_model", None) for v in getattr(recon, "views", [])}
    for n, r in enumerate(_insertions(report)):
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
        tds = "".join(f"<td>{c}</td>" for c in cells)
        rows.append(f'<tr class="{cls}" data-status="{html.escape(status)}">{tds}</tr>')
    head = "".join(f"<th>{html.escape(c)}</th>" for c in _COLUMNS)
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
tr.failed td{background:#fde8e8;color:#8a1c1c}tr.pair td{background:#fff4e5}
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
  });
  document.body.setAttribute('data-rendered', 'true');
})();
"""


def render_report_html(recon: Any, report: dict[str, Any], title: str | None = None) -> str:
    """The report's HTML text (see :func:`write_report_html`); optional parts that fail are
    logged and left out."""
    report = report if isinstance(report, dict) else {}
    sparse = _optional("the sparse cloud", lambda: _finite_cloud(*recon.live_points()))
    if sparse is None:
        sparse = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    cams = _optional("the cameras", lambda: _registered_cameras(recon)) or []
    frame = _optional("the scene frame", lambda: _scene_frame(sparse[0], np.array([_center(P) for _, _, P, _ in cams]).reshape(-1, 3)))
    figures: dict[str, Any] = {}
    if frame is not None:
        fig = _optional("the 3D view", lambda: _figure_3d(recon, frame, sparse, cams))
        if fig is not None and fig["data"]:
            figures["view3d"] = {**fig, "webgl": True}
        fig = _optional("the camera path", lambda: _figure_path(frame, sparse[0], cams))
        if fig is not None and fig["data"]:
            figures["path"] = fig
    for key, what, build in (("reprojection", "the reprojection plot", _figure_reprojection),
                             ("times", "the time plot", _figure_times)):
        fig = _optional(what, lambda: build(report))
        if fig is not None:
            figures[key] = fig
    matches = _optional("the weakest insertion's matches", lambda: _weakest_insertion(recon, report))
    summary = _optional("the summary", lambda: _summary(recon, report)) or ""
    table = _optional("the per-image table", lambda: _table(recon, report)) or '<p class="note">no per-image report</p>'
    encoded = {key: _optional(f"figure {key!r}", lambda: _json_for_script(fig)) for key, fig in figures.items()}
    figures = {key: fig for key, fig in figures.items() if encoded[key] is not None}
    plotly_js = _optional("the Plotly bundle", _plotly_js) if figures else None
    if plotly_js is None:
        figures = {}

    def plot_section(key: str, heading: str, note: str = "") -> str:
        if key not in figures:
            return ""
        extra = f'<p class="note">{note}</p>' if note else ""
        return f'<section><h2>{heading}</h2>{extra}<div id="{key}" class="plot"></div></section>'

    title = title or "stereoseed reconstruction"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f'<header><h1>{html.escape(title)}</h1><div class="summary">{summary}</div></header><main>',
        plot_section("view3d", "3D view",
                     "Sparse cloud (coloured), dense cloud when computed (subsampled), and a frustum per registered "
                     "camera (orange: the calibrated pair; the tick marks the top of the image). Drag to rotate, "
                     "scroll to zoom, hover a frustum for its image; click a legend entry to hide it."),
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
        parts.append(f"<script>{_SCRIPT}</script>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


def _plotly_js() -> str:
    from plotly.offline import get_plotlyjs

    return get_plotlyjs()


def write_report_html(recon: Any, report: dict[str, Any], out_dir: str | Path) -> Path:
    """Write ``out_dir/report.html``, one self-contained file (no network), atomically (a
    temporary file in out_dir replaces it). Returns its path.

    recon: the :class:`~stereoseed.reconstruction.Reconstruction` (its dense cloud is shown
    when :func:`stereoseed.dense.densify` ran); report: the run's report dict (report.json).
    A part that cannot be built is logged and left out; only an error writing the file raises.
    """
    path = Path(out_dir) / "report.html"
    text = render_report_html(recon, report, title=f"stereoseed reconstruction: {path.parent.resolve().name}")
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    log.info("wrote %s (%.1f MB)", path, len(text) / 1e6)
    return path
