"""The reconstruction's data model: views (images with their camera and interest points), 3D
points with colour, and observations linking an interest point of a view to a 3D point.

Modelled on COLMAP's Camera/Image/Point3D: a point's track is the list of its observations.
Everything is kept in flat NumPy arrays so the pipeline's steps stay vectorised.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .camera import project
from .features import Features
from .io import camera_entry, write_json, write_ply

__all__ = ["View", "Reconstruction"]


@dataclass
class View:
    """One input image.

    name: file name; features: its interest points; P: (3, 4) or None while unregistered;
    status: "calibrated", "registered", "pending" or "failed: <reason>";
    point_of_feature: (N,) int64, the 3D point an interest point currently stands for (-1: none).
    image: uint8 BGR (H, W, 3), kept while the run needs it (colours, dense stage).
    """

    name: str
    features: Features | None = None
    P: np.ndarray | None = None
    status: str = "pending"
    point_of_feature: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    image: np.ndarray | None = None
    rotated_180: bool = False  # the run works on the image turned upside down (camera held so)
    camera_model: str | None = None  # set when the view needed another model than the run's
    zoomed: bool = False  # its resection took a new focal length (rather than the previous image's)

    @property
    def registered(self) -> bool:
        return self.P is not None

    @property
    def P_input(self) -> np.ndarray | None:
        """P (3, 4) in the pixel frame of the input image (P works in the frame the run used:
        the image turned by 180 degrees when ``rotated_180``)."""
        if self.P is None or not self.rotated_180:
            return self.P
        h, w = self.image.shape[:2]
        flip = np.array([[-1.0, 0.0, w - 1.0], [0.0, -1.0, h - 1.0], [0.0, 0.0, 1.0]])
        return flip @ self.P


class Reconstruction:
    """Views, points (M, 3) with colours (M, 3) uint8 RGB, and observations.

    Observations are three parallel int64 arrays (obs_view, obs_feature, obs_point): interest
    point ``obs_feature`` of view ``obs_view`` is an image of 3D point ``obs_point``. Removed
    points keep their index (``alive`` is False) so indices held elsewhere stay valid.
    """

    def __init__(self, views: list[View]):
        self.views = views
        self.points = np.zeros((0, 3))
        self.colors = np.zeros((0, 3), np.uint8)
        self.alive = np.zeros(0, bool)
        self.obs_view = np.zeros(0, np.int64)
        self.obs_feature = np.zeros(0, np.int64)
        self.obs_point = np.zeros(0, np.int64)
        self.source: Any = None  # where correspondences come from (set by the pipeline)

    # ------------------------------------------------------------ building
    def add_points(self, points: np.ndarray, colors: np.ndarray) -> np.ndarray:
        """Append points (K, 3) with colours (K, 3); returns their ids (K,)."""
        ids = np.arange(len(self.points), len(self.points) + len(points))
        self.points = np.vstack([self.points, points])
        self.colors = np.vstack([self.colors, np.asarray(colors, np.uint8).reshape(-1, 3)])
        self.alive = np.concatenate([self.alive, np.ones(len(points), bool)])
        return ids

    def add_observations(self, view: int, features: np.ndarray, point_ids: np.ndarray,
                         link: bool = True) -> None:
        """Record that ``features`` (K,) of ``view`` observe ``point_ids`` (K,).

        link: also make those interest points stand for the points (``point_of_feature``).
        """
        features = np.asarray(features, np.int64)
        point_ids = np.asarray(point_ids, np.int64)
        self.obs_view = np.concatenate([self.obs_view, np.full(len(features), view, np.int64)])
        self.obs_feature = np.concatenate([self.obs_feature, features])
        self.obs_point = np.concatenate([self.obs_point, point_ids])
        if link:
            self.views[view].point_of_feature[features] = point_ids

    def remove_observations(self, mask: np.ndarray) -> None:
        """Drop the observations selected by mask (O,) and unlink their interest points."""
        for v in np.unique(self.obs_view[mask]):
            sel = mask & (self.obs_view == v)
            pof = self.views[v].point_of_feature
            f = self.obs_feature[sel]
            linked = pof[f] == self.obs_point[sel]
            pof[f[linked]] = -1
        keep = ~mask
        self.obs_view, self.obs_feature, self.obs_point = (self.obs_view[keep], self.obs_feature[keep],
                                                           self.obs_point[keep])

    def remove_points(self, point_ids: np.ndarray) -> None:
        """Mark points dead and drop their observations."""
        point_ids = np.asarray(point_ids, np.int64)
        if len(point_ids) == 0:
            return
        self.alive[point_ids] = False
        self.remove_observations(~self.alive[self.obs_point])

    # ------------------------------------------------------------ queries
    def observation_xy(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Pixels (O, 2) of the observations (optionally a subset)."""
        views = self.obs_view if mask is None else self.obs_view[mask]
        feats = self.obs_feature if mask is None else self.obs_feature[mask]
        out = np.empty((len(views), 2))
        for v in np.unique(views):
            sel = views == v
            out[sel] = self.views[v].features.points[feats[sel]]
        return out

    def observation_errors(self) -> np.ndarray:
        """Reprojection distance (px) of every observation, (O,)."""
        err = np.empty(len(self.obs_view))
        xy = self.observation_xy()
        for v in np.unique(self.obs_view):
            sel = self.obs_view == v
            err[sel] = np.linalg.norm(project(self.views[v].P, self.points[self.obs_point[sel]]) - xy[sel], axis=1)
        return err

    def track_lengths(self) -> np.ndarray:
        return np.bincount(self.obs_point, minlength=len(self.points))

    @property
    def registered_views(self) -> list[int]:
        return [i for i, v in enumerate(self.views) if v.registered]

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (K, 3), colours (K, 3)) of the points still alive and observed."""
        keep = self.alive & (self.track_lengths() >= 2)
        return self.points[keep], self.colors[keep]

    def reprojection_summary(self) -> dict[str, float]:
        """RMS (px) over observations and the paper's eq. 14: sum of squared errors / (m n),
        m registered images, n points (reported squared, not rooted, as printed)."""
        if len(self.obs_view) == 0:
            return {"rms_px": float("nan"), "eq14": float("nan"), "observations": 0}
        err = self.observation_errors()
        n_pts = int(np.sum(self.alive & (self.track_lengths() > 0)))
        m = len(self.registered_views)
        return {"rms_px": float(np.sqrt(np.mean(err ** 2))),
                "eq14": float(np.sum(err ** 2) / max(1, m * n_pts)),
                "observations": int(len(err))}

    # ------------------------------------------------------------ output
    def cameras_dict(self) -> dict[str, Any]:
        images = []
        for v in self.views:
            entry: dict[str, Any] = {"name": v.name, "registered": v.registered, "status": v.status}
            if v.registered:
                entry.update(camera_entry(v.P_input))
                if v.rotated_180:
                    entry["rotated_180"] = True
            images.append(entry)
        return {"convention": "P maps world (pattern frame) to pixels; pixel (0,0) = centre of the top-left pixel; "
                              "R, t are cam_from_world",
                "images": images}

    def save(self, out_dir: str | Path) -> dict[str, Path]:
        """Write cameras.json and sparse.ply into out_dir (atomically)."""
        out = Path(out_dir)
        pts, cols = self.live_points()
        return {"cameras": write_json(out / "cameras.json", self.cameras_dict()),
                "sparse": write_ply(out / "sparse.ply", pts, cols)}
