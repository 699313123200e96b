"""What the live page shows of a run as it stands: a row per photo (its status, why it was
skipped, its flag), the last photo's status, what to do next, and the 3D view built by
report.html's own figure code (:func:`stereoseed.output.report.figures.figure_3d`)."""
from __future__ import annotations

import base64
import logging
from typing import Any

import cv2
import numpy as np

from stereoseed.geometry.projection import camera_center
from stereoseed.output.report.figures import figure_3d, finite_cloud, optional_part, registered_cameras, scene_frame

__all__ = ["page_state", "last_photo", "COVERAGE_GAP_DEG", "FAILURES_IN_A_ROW", "LAST_PHOTO_WIDTH"]

log = logging.getLogger(__name__)

# A ring around the object whose largest gap between neighbouring cameras (seen from the object,
# in the ground plane) is wider than this is not closed yet: at 30 degrees between photos a
# textured object still matches (the 36-image ring: 10 degrees), beyond 45 the walk has a side
# left to photograph.
COVERAGE_GAP_DEG = 45.0
# The last photo is shown this wide (px): enough to see what it shows and where its points are,
# a JPEG of a few tens of kB pushed with each state.
LAST_PHOTO_WIDTH = 480
# This many photos in a row that did not register: the walk has left what the model knows
# (a photo or two may be blurred; three are a lost track).
FAILURES_IN_A_ROW = 3


def _rows(recon: Any, names: list[str], reports: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for i, name in enumerate(names):
        if i < len(reports):
            r = reports[i]
            flag = recon.views[i].flag_reason if recon.views[i].registered else None
            rows.append({"image": name, "status": str(r.get("status", "")), "reason": r.get("reason"), "flag": flag})
        else:
            rows.append({"image": name, "status": "waiting" if i >= 2 or len(names) < 2 else "pair",
                         "reason": None, "flag": None})
    return rows


def _gap(cams: list, frame: dict[str, Any]) -> tuple[float, float, str] | None:
    """(start, end (degrees around the object, in the ground plane), the camera before the gap) of
    the widest angle between neighbouring cameras, or None with fewer than three cameras."""
    if len(cams) < 3:
        return None
    centres = np.array([camera_center(P) for _, _, P, _ in cams]) - frame["target"]
    angles = np.degrees(np.arctan2(centres @ frame["e2"], centres @ frame["e1"])) % 360.0
    order = np.argsort(angles)
    a = angles[order]
    gaps = np.diff(np.append(a, a[0] + 360.0))
    j = int(np.argmax(gaps))
    return float(a[j]), float(a[j] + gaps[j]) % 360.0, cams[order[j]][1]


def _hints(rows: list[dict[str, Any]], cams: list, frame: dict[str, Any] | None) -> list[str]:
    """What the user should do next, most urgent first."""
    if len(rows) < 2:
        return ["Waiting for the calibrated pair: the two photos taken by the two calibrated cameras come first."]
    reached = [r for r in rows if r["status"] != "waiting"]
    good = [r["image"] for r in reached if r["status"] in ("registered", "calibrated pair", "calibrated")]
    hints = []
    last = reached[-1] if reached else None
    if last is not None and last["status"] == "failed":
        row = next((i for i, r in enumerate(reversed(reached)) if r["status"] != "failed"), len(reached))
        back = good[-1] if good else rows[0]["image"]
        if row >= FAILURES_IN_A_ROW:
            hints.append(f"{row} photos in a row did not register: the walk has left what the model knows. Go back to "
                         f"where you took {back} and start again from there, in small steps.")
        hints.append(f"{last['image']} did not register ({last['reason']}). Move back towards the last good view, "
                     f"{back}, and take the next photo from near it, overlapping it by most of the picture.")
    elif last is not None and last.get("flag"):
        hints.append(f"{last['image']} is placed but flagged ({last['flag']}): take one more photo near it, so the "
                     f"next one confirms it.")
    if frame is not None:
        gap = _gap(cams, frame)
        if gap is not None and (gap[1] - gap[0]) % 360.0 > COVERAGE_GAP_DEG:
            hints.append(f"No photo yet from the side between {gap[0]:.0f}° and {gap[1]:.0f}° around the object "
                         f"(after {gap[2]}): walk on around it to close the ring.")
    if not hints:
        hints.append("Good: take the next photo a small step further around the object, overlapping the last one.")
    return hints


def last_photo(recon: Any, k: int) -> str | None:
    """The last photo reached, small, as a JPEG data URI: its interest points that observe a
    point of the model drawn green (its matches with the model), the others grey (``k``: its
    view); None before the pair."""
    if recon is None or k < 0:
        return None
    view = recon.views[k]
    image = view.image
    if image is None or image.size == 0 or 0 in image.strides:  # (an unreadable photo reads as a blank of no memory)
        return None
    scale = min(1.0, LAST_PHOTO_WIDTH / image.shape[1])
    small = (cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1.0
             else np.array(image))  # a copy to draw on: the sequence's images are shared, read-only
    features = view.features
    if features is not None and len(features.points):
        linked = np.asarray(view.point_of_feature) >= 0
        for points, colour, radius in ((features.points[~linked], (150, 150, 150), 1),
                                       (features.points[linked], (60, 220, 60), 3)):
            for x, y in np.round(points * scale).astype(int):
                cv2.circle(small, (int(x), int(y)), radius, colour, -1, cv2.LINE_AA)
    ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return "data:image/jpeg;base64," + base64.b64encode(jpeg.tobytes()).decode("ascii") if ok else None


def page_state(recon: Any, names: list[str], unit: str | None = None, with_figure: bool = True) -> dict[str, Any]:
    """The page's state (JSON-able): counts, a row per photo, the last photo's row, the hints,
    and the 3D view's Plotly figure (None before the pair, or when it cannot be built)."""
    reports = recon.reports() if recon is not None else []  # every view's history rendered once
    rows = _rows(recon, names, reports)
    cams = (optional_part("the cameras", lambda: registered_cameras(recon)) or []) if recon is not None else []
    figure = frame = None
    points = 0
    if recon is not None:
        sparse = optional_part("the sparse cloud", lambda: finite_cloud(*recon.live_points()))
        if sparse is None:
            sparse = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
        points = len(sparse[0])
        centres = np.array([camera_center(P) for _, _, P, _ in cams]).reshape(-1, 3)
        frame = optional_part("the scene frame", lambda: scene_frame(sparse[0], centres))
        if frame is not None and with_figure:
            figure = optional_part("the 3D view", lambda: figure_3d(None, frame, sparse, cams, unit))
    reached = [r for r in rows if r["status"] != "waiting"]
    return {"photos": len(names), "cameras": len(cams), "points": int(points),
            "flagged": sum(1 for r in rows if r.get("flag")),
            "skipped": sum(1 for r in rows if r["status"] == "failed"),
            "last": reached[-1] if reached else (rows[-1] if rows else None),
            "rows": rows, "hints": _hints(rows, cams, frame), "figure": figure,
            "last_photo": optional_part("the last photo", lambda: last_photo(recon, len(reports) - 1)) if with_figure else None}
