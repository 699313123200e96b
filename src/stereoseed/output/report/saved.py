"""report.html written again from what a result folder holds (``stereoseed mesh`` adds the mesh
it made to the page of the run that made the cloud).

The page's renderer (:func:`stereoseed.output.report.html.render_report_html`) reads a run's
reconstruction; a result folder holds its cameras and points (cameras.json, tracks.npz, read by
:func:`stereoseed.output.reader.load_result`), its report (report.json) and its dense cloud
(dense.ply). :class:`SavedReconstruction` gives the renderer those, as the run's reconstruction
would: the views' names, cameras and sizes, the sparse points. What only a run holds (the
images, their features: the weakest insertion's matches) is left out of the page.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.output.reader import Result, load_result
from stereoseed.output.report.html import write_report_html
from stereoseed.output.result_set import MANIFEST, read_manifest

__all__ = ["SavedCloud", "SavedReconstruction", "SavedView", "rewrite_report_html"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SavedView:
    """One image of a result folder as the page reads a view: P_input and P are the camera in
    the input image's frame (None: not registered); no features, no image."""

    name: str
    P_input: np.ndarray | None
    image_size: tuple[int, int]
    features: None = None

    @property
    def registered(self) -> bool:
        return self.P_input is not None

    @property
    def P(self) -> np.ndarray | None:
        return self.P_input


class SavedReconstruction:
    """A result folder's cameras and sparse points as the report page reads a reconstruction."""

    def __init__(self, result: Result, rig: bool = False) -> None:
        self.views = [SavedView(n, P, tuple(s)) for n, P, s in zip(result.names, result.P, result.sizes)]
        self.rig = True if rig else None  # the page only asks whether the walk was a rig's
        self._points = np.asarray(result.tracks["point_xyz"], np.float64).reshape(-1, 3)
        self._colors = np.asarray(result.tracks["point_rgb"]).reshape(-1, 3)

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        """The points tracks.npz holds (the run wrote only the observed ones) and their colours."""
        return self._points, self._colors

    def registered_before(self, k: int, n: int) -> list[int]:
        """The last ``n`` registered views before view ``k``, nearest first."""
        return [i for i in range(k - 1, -1, -1) if self.views[i].registered][:n]


@dataclass(frozen=True)
class SavedCloud:
    """dense.ply's points and colours, as the page shows the dense cloud."""

    points: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def _is_rig(folder: Path) -> bool:
    try:
        images = json.loads((folder / "cameras.json").read_text(encoding="utf-8"))["images"]
        return any(isinstance(im, dict) and "station" in im for im in images)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def rewrite_report_html(folder: str | Path, mesh: Any = None, cloud: SavedCloud | None = None,
                        report_update: dict[str, Any] | None = None) -> Path | None:
    """Write ``folder/report.html`` again from the folder's files, with ``mesh`` (a
    :class:`~stereoseed.dense.mesh.Mesh`) shown; ``cloud``: the dense cloud when the caller has
    it read already (else dense.ply is read); ``report_update``: keys set in report.json too
    (written again first, so the page and the file agree). The caller holds the folder's lock.

    Only what stereoseed wrote is touched: report.html and report.json when the folder's
    manifest lists them. Returns report.html's path, or None (logged) when the folder has no
    report.html of stereoseed's, or its cameras.json / tracks.npz cannot be read."""
    from stereoseed.errors import StereoseedError
    from stereoseed.io.atomic import write_json
    from stereoseed.io.ply import read_ply

    folder = Path(folder)
    listed = read_manifest(folder / MANIFEST)
    if listed is None or "report.html" not in listed:
        log.info("%s: no report.html of stereoseed's (no manifest listing it): none written", folder)
        return None
    try:
        result = load_result(folder)
    except StereoseedError as e:
        log.warning("%s; report.html is left as it is", e)
        return None
    report: dict[str, Any] = {}
    if "report.json" in listed:
        try:
            loaded = json.loads((folder / "report.json").read_text(encoding="utf-8"))
            report = loaded if isinstance(loaded, dict) else {}
        except (OSError, ValueError):
            log.warning("%s: unreadable; report.html is written without the run's report", folder / "report.json")
        if report and report_update:
            report.update(report_update)
            write_json(folder / "report.json", report)
    if cloud is None and (folder / "dense.ply").is_file():
        points, colors = read_ply(folder / "dense.ply")
        cloud = SavedCloud(points, colors)
    return write_report_html(SavedReconstruction(result, _is_rig(folder)), report, folder, dense=cloud, mesh=mesh)
