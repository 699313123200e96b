"""The figures of ``report.html`` (:mod:`stereoseed.output.report.html`) as Plotly figure dicts: the
3D view of the clouds and camera frustums, the camera path from above, the reprojection error
and the time of each insertion. Pure functions of the reconstruction and its report."""
from __future__ import annotations

import logging
import math
from typing import Any, Callable

import numpy as np

from stereoseed.geometry.projection import backproject, camera_center, is_finite_camera, viewing_direction
from stereoseed.output.report.measure import measure_spec, measurement_trace, scale_bar, unit_label

# a stereo rig's bar from each station's left camera to its right: cyan, apart from the scale
# bar's yellow (measure.SCALE_COLOUR), the frustums' orange and red and the clouds' colours
RIG_COLOUR = "#17becf"

log = logging.getLogger("stereoseed.output.report.html")  # one logger for the whole report

MAX_DENSE_POINTS = 50_000  # the dense cloud is subsampled to this many points
MAX_MESH_FACES = 100_000  # a larger mesh shows this many of its faces (a few MB of the page)


MAX_SPARSE_POINTS = 50_000


FRUSTUM_DEPTH = 0.07  # frustum depth as a fraction of the scene size


_TIME_PARTS = ("features", "matching", "resection", "triangulation", "bundle")

# Plotly's toolbar (its modebar) sits in the top right corner of a plot when the mouse is over it:
# the 2D plots keep this margin above their plotting area free for it and put their legends to the
# right of the area, below the margin; the 3D view's legend sits in its bottom left corner
TOOLBAR_MARGIN_PX = 36
_LEGEND_RIGHT = {"x": 1.02, "xanchor": "left", "y": 1.0, "yanchor": "top"}


# ---------------------------------------------------------------- small helpers


def optional_part(what: str, build: Callable[[], Any]) -> Any:
    """build(), or None (logged) when it fails: no part of the report may fail the run."""
    try:
        return build()
    except Exception as e:  # noqa: BLE001 - the report is optional, the reconstruction is not
        log.warning("report.html: %s left out (%s: %s)", what, type(e).__name__, e)
        log.debug("report.html: %s", what, exc_info=True)
        return None


def finite_number(value: Any) -> float | None:
    """A finite float, or None."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


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


def finite_cloud(points: Any, colors: Any) -> tuple[np.ndarray, np.ndarray]:
    if points is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    cols = (np.full((len(pts), 3), 128, np.uint8) if colors is None or len(colors) != len(pts)
            else np.asarray(colors).reshape(-1, 3))
    ok = np.all(np.isfinite(pts), axis=1)
    return pts[ok], cols[ok]


# ---------------------------------------------------------------- geometry


def registered_cameras(recon: Any) -> list[tuple[int, str, np.ndarray, tuple[int, int]]]:
    """(index, name, P_input, (width, height)) of each registered view with a finite camera."""
    cams = []
    for i, v in enumerate(recon.views):
        try:
            P = v.P_input
            if P is None or not is_finite_camera(P):
                continue
            cams.append((i, str(v.name), np.asarray(P, np.float64), tuple(v.image_size)))
        except Exception as e:  # noqa: BLE001
            log.debug("report.html: view %d has no usable camera (%s)", i, e)
    return cams


def scene_frame(points: np.ndarray, centers: np.ndarray) -> dict[str, Any]:
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


def figure_3d(dense_cloud: Any, frame: dict[str, Any], sparse: tuple[np.ndarray, np.ndarray],
               cams: list[tuple[int, str, np.ndarray, tuple[int, int]]], unit: str | None = None,
               mesh: Any = None, rig: bool = False) -> dict[str, Any]:
    """The mesh (when given; a legend click shows or hides it), the clouds (a click picks a point:
    "hoverinfo" none, not skip), the frustums (on a ``rig`` walk each station's two centres
    joined: views 2s and 2s + 1), a scale bar and the (empty) trace the page's script draws a
    measured distance in (``fig["measure"]``)."""
    size = frame["size"]
    data: list[dict[str, Any]] = []
    if mesh is not None and len(mesh.faces):
        faces = mesh.faces
        if len(faces) > MAX_MESH_FACES:
            faces = faces[np.random.default_rng(0).choice(len(faces), MAX_MESH_FACES, replace=False)]
        v = mesh.vertices
        data.append({"type": "mesh3d", "name": f"mesh ({len(faces)} of {len(mesh.faces)} faces)", "showlegend": True,
                     "x": _rounded(v[:, 0], size), "y": _rounded(v[:, 1], size), "z": _rounded(v[:, 2], size),
                     "i": faces[:, 0].tolist(), "j": faces[:, 1].tolist(), "k": faces[:, 2].tolist(),
                     "vertexcolor": _hex_colors(mesh.colors), "flatshading": False, "hoverinfo": "none",
                     "lighting": {"ambient": 0.7, "diffuse": 0.5}})
    dense = None if dense_cloud is None else optional_part(
        "the dense cloud", lambda: finite_cloud(dense_cloud.points, dense_cloud.colors))
    if dense is not None and len(dense[0]):
        near_pts, near_cols, far = _shown(*dense, frame)
        pts, cols = _subsample(near_pts, near_cols, MAX_DENSE_POINTS)
        n_all = len(dense[0])
        data.append({"type": "scatter3d", "mode": "markers", "name": f"dense ({len(pts)} of {n_all} points{far})",
                     "x": _rounded(pts[:, 0], size), "y": _rounded(pts[:, 1], size), "z": _rounded(pts[:, 2], size),
                     "marker": {"size": 1.2, "color": _hex_colors(cols)}, "hoverinfo": "none"})
    near_pts, near_cols, far = _shown(*sparse, frame)
    pts, cols = _subsample(near_pts, near_cols, MAX_SPARSE_POINTS)
    if len(pts):
        data.append({"type": "scatter3d", "mode": "markers", "name": f"sparse ({len(sparse[0])} points{far})",
                     "x": _rounded(pts[:, 0], size), "y": _rounded(pts[:, 1], size), "z": _rounded(pts[:, 2], size),
                     "marker": {"size": 2.0 if dense is None or not len(dense[0]) else 1.5, "color": _hex_colors(cols)},
                     "hoverinfo": "none"})
    depth = FRUSTUM_DEPTH * size
    groups: dict[str, list] = {"calibrated pair": [], "registered": []}
    for i, name, P, (w, h) in cams:
        corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])
        c = camera_center(P)
        q = backproject(P, corners, depth)
        top = backproject(P, np.array([[(w - 1) / 2.0, -0.25 * h]]), depth)[0]  # the 'up' tick above the image
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
    centres = np.array([camera_center(P) for _, _, P, _ in cams]).reshape(-1, 3)
    if rig:
        centre_of = {i: c for (i, _, _, _), c in zip(cams, centres)}
        xyz = [[], [], []]
        for i in sorted(centre_of):
            if i % 2 == 0 and i + 1 in centre_of:
                for d in range(3):
                    xyz[d] += [float(centre_of[i][d]), float(centre_of[i + 1][d]), None]
        if xyz[0]:
            data.append({"type": "scatter3d", "mode": "lines", "name": "stereo rig (each station)", "x": xyz[0],
                         "y": xyz[1], "z": xyz[2], "line": {"color": RIG_COLOUR, "width": 6}, "hoverinfo": "none"})
    if cams:
        data.append({"type": "scatter3d", "mode": "markers", "name": "camera centres", "showlegend": False,
                     "x": _rounded(centres[:, 0], size), "y": _rounded(centres[:, 1], size),
                     "z": _rounded(centres[:, 2], size), "text": [f"{i}: {n}" for i, n, _, _ in cams],
                     "marker": {"size": 3, "color": "#ffffff", "line": {"color": "#d62728", "width": 1}},
                     "hovertemplate": "%{text}<extra></extra>"})
    data.append(scale_bar(frame, near_pts, unit))
    data.append(measurement_trace())
    measure = measure_spec(unit, trace=len(data) - 1, skip=[len(data) - 2])
    up = frame["up"]
    # look from outside the ring, slightly above it, at the scene's centre
    side = frame["e1"] * 0.9 + frame["e2"] * 0.9
    eye = side + up * 0.9
    layout = {
        "margin": {"l": 0, "r": 0, "t": 0, "b": 0}, "paper_bgcolor": _DARK, "font": {"color": "#e6e6e6"},
        "legend": {"x": 0.01, "xanchor": "left", "y": 0.01, "yanchor": "bottom", "bgcolor": "rgba(0,0,0,0.35)"},
        "scene": {"aspectmode": "data", "bgcolor": _DARK,
                  **{f"{a}axis": {"title": {"text": f"{a.upper()} ({unit_label(unit)})"}, "color": "#9aa3b5",
                                  "gridcolor": "#394050"} for a in "xyz"},
                  "camera": {"up": dict(zip("xyz", map(float, up))), "eye": dict(zip("xyz", map(float, eye))),
                             "center": {"x": 0, "y": 0, "z": 0}}},
        "uirevision": "keep",
    }
    return {"data": data, "layout": layout, "measure": measure}


def figure_path(frame: dict[str, Any], sparse: np.ndarray,
                 cams: list[tuple[int, str, np.ndarray, tuple[int, int]]], unit: str | None = None) -> dict[str, Any]:
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
        c = np.array([camera_center(P) for _, _, P, _ in cams])
        d = np.array([viewing_direction(P) for _, _, P, _ in cams])
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
    layout = {"margin": {"l": 50, "r": 10, "t": TOOLBAR_MARGIN_PX, "b": 40}, "showlegend": False,
              "xaxis": {"title": {"text": f"{labels[0]} ({unit_label(unit)})"}, "zeroline": False},
              "yaxis": {"title": {"text": f"{labels[1]} ({unit_label(unit)})"}, "zeroline": False, "scaleanchor": "x",
                        "scaleratio": 1}}
    return {"data": data, "layout": layout}


def insertions(report: dict[str, Any]) -> list[dict[str, Any]]:
    return [r for r in report.get("per_image") or [] if isinstance(r, dict)]


def figure_reprojection(report: dict[str, Any]) -> dict[str, Any] | None:
    names, before, after = [], [], []
    for r in insertions(report):
        ba = r.get("ba") if isinstance(r.get("ba"), dict) else {}
        b, a = finite_number(ba.get("rms_before_px")), finite_number(ba.get("rms_after_px"))
        if b is None and a is None:
            continue
        names.append(str(r.get("image", "?")))
        before.append(b)
        after.append(a)
    final = (report.get("final") or {}).get("final_ba") if isinstance(report.get("final"), dict) else None
    if isinstance(final, dict) and (finite_number(final.get("rms_before_px")) is not None):
        names.append("final BA")
        before.append(finite_number(final.get("rms_before_px")))
        after.append(finite_number(final.get("rms_after_px")))
    if not names:
        return None
    data = [{"type": "bar", "name": "before BA", "x": names, "y": before, "marker": {"color": "#ff7f0e"}},
            {"type": "bar", "name": "after BA", "x": names, "y": after, "marker": {"color": "#2ca02c"}}]
    layout = {"barmode": "group", "margin": {"l": 55, "r": 10, "t": TOOLBAR_MARGIN_PX, "b": 90},
              "yaxis": {"title": {"text": "reprojection RMS (px)"}, "rangemode": "tozero"},
              "xaxis": {"type": "category", "tickangle": -45}, "legend": _LEGEND_RIGHT}
    return {"data": data, "layout": layout}


def figure_times(report: dict[str, Any]) -> dict[str, Any] | None:
    rows = [r for r in insertions(report) if isinstance(r.get("seconds"), dict)]
    if not rows:
        return None
    names = [str(r.get("image", "?")) for r in rows]
    data = []
    for part in _TIME_PARTS + ("other",):
        ys = []
        for r in rows:
            s = r["seconds"]
            if part == "other":
                total = finite_number(s.get("total"))
                known = sum(finite_number(s.get(p)) or 0.0 for p in _TIME_PARTS)
                ys.append(max(0.0, total - known) if total is not None else None)
            else:
                ys.append(finite_number(s.get(part)))
        if any(y for y in ys):
            data.append({"type": "bar", "name": part, "x": names, "y": ys})
    layout = {"barmode": "stack", "margin": {"l": 55, "r": 10, "t": TOOLBAR_MARGIN_PX, "b": 90},
              "yaxis": {"title": {"text": "seconds"}, "rangemode": "tozero"},
              "xaxis": {"type": "category", "tickangle": -45}, "legend": _LEGEND_RIGHT}
    return {"data": data, "layout": layout}


# ---------------------------------------------------------------- the weakest insertion's matches
