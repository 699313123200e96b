"""The result folder: everything a run leaves on disk, written and read back in one place
(OpenSfM's DataSet does this job for its pipeline).

Written by :func:`write_result` (atomically, file by file):

* ``cameras.json`` — per input image: name, width, height, registered, status and, when
  registered, P, K, R, t, centre (our conventions: P maps world to pixels, pixel (0, 0) is the
  centre of the top-left pixel, R, t cam_from_world);
* ``tracks.npz`` — the observations (which pixel of which image belongs to which 3D point),
  documented in docs/formats.md;
* ``sparse.ply`` — the points with colour, mean reprojection error, track length and number of
  views; ``cameras.ply`` — a small frustum per registered camera;
* ``report.json`` — the run's report.

The coordinates are in the calibration's unit; cameras.json's ``unit`` names it when the
calibration did (calib.json ``unit``, the report's ``unit``).

Far outliers are left out of every export (:func:`exported_points`).
:func:`stereoseed.output.reader.load_result` reads a folder back; :class:`stereoseed.output.result_set.ResultSet`
writes it as a whole (a staging folder swapped in at the end).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.geometry.camera import Camera
from stereoseed.geometry.lens import lens_index
from stereoseed.arrays import distinct_pair_firsts
from stereoseed.geometry.projection import backproject, camera_center
from stereoseed.config import Config
from stereoseed.io.files import atomic_path, write_json
from stereoseed.io.ply import write_ply
from stereoseed.scene.reconstruction import Reconstruction, View

__all__ = ["FORMAT_VERSION", "exported_points", "write_result", "frustum_mesh"]

FORMAT_VERSION = 1


def exported_points(recon: Reconstruction, max_distance_factor: float) -> np.ndarray:
    """Ids of the points that leave the tool: alive, seen at least twice, and not far outliers.
    A point is a far outlier when it lies farther from the median point than
    ``max_distance_factor`` times the registered cameras' median distance to that median point
    (a point triangulated from nearly parallel rays can land metres away from a 10 cm object)."""
    ids = np.flatnonzero(recon.alive & (recon.track_lengths() >= 2))
    if len(ids) == 0:
        return ids
    pts = recon.points[ids]
    centre = np.median(pts, axis=0)
    return ids[np.linalg.norm(pts - centre, axis=1) <= max_distance_factor * _camera_distance(recon, centre)]


def _camera_distance(recon: Reconstruction, centre: np.ndarray) -> float:
    """The registered cameras' median distance to ``centre`` (3,): the scale of the scene."""
    return float(np.median([np.linalg.norm(recon.views[v].center - centre) for v in recon.registered_views]))


def _input_frame(view: View, xy: np.ndarray) -> np.ndarray:
    """Pixels xy (N, 2) of the frame the run used for ``view`` in its input image's frame."""
    if not view.rotated_180:
        return xy
    w, h = view.image_size
    return np.array([w - 1.0, h - 1.0]) - xy


def tracks_arrays(recon: Reconstruction, ids: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of tracks.npz for the points ``ids`` (see docs/formats.md)."""
    n_images = len(recon.views)
    new_id = np.full(len(recon.points), -1, np.int64)
    new_id[ids] = np.arange(len(ids))
    sel = new_id[recon.obs_point] >= 0
    errors = recon.observation_errors()[sel]
    obs_view, obs_feature, obs_point = recon.obs_view[sel], recon.obs_feature[sel], new_id[recon.obs_point[sel]]
    order = np.lexsort((obs_feature, obs_view))  # image by image, as the keypoints
    obs_view, obs_feature, obs_point, errors = obs_view[order], obs_feature[order], obs_point[order], errors[order]
    keypoints, obs_keypoint, offsets = [], np.empty(len(obs_view), np.int64), [0]
    for v in range(n_images):
        view = recon.views[v]
        xy = _input_frame(view, view.features.points) if view.registered and view.features is not None \
            else np.zeros((0, 2))
        here = np.arange(*np.searchsorted(obs_view, [v, v + 1]))  # obs_view is sorted
        # an interest point observing two points (the paper mode's unlinked observations) gets a
        # copy per extra point: a 2D point of COLMAP's model belongs to one 3D point
        first = np.ones(len(here), bool)
        first[1:] = obs_feature[here][1:] != obs_feature[here][:-1]
        extra = here[~first]
        obs_keypoint[here[first]] = obs_feature[here[first]]
        obs_keypoint[extra] = len(xy) + np.arange(len(extra))
        keypoints.append(np.vstack([xy, xy[obs_feature[extra]]]) if len(extra) else xy)
        offsets.append(offsets[-1] + len(keypoints[-1]))
    point_error = (np.bincount(obs_point, weights=errors, minlength=len(ids))
                   / np.maximum(np.bincount(obs_point, minlength=len(ids)), 1))
    return {"format_version": np.array(FORMAT_VERSION), "point_xyz": recon.points[ids],
            "point_rgb": recon.colors[ids], "point_error": point_error,
            "obs_point": obs_point, "obs_image": obs_view, "obs_keypoint": obs_keypoint,
            "keypoints_xy": np.vstack(keypoints), "keypoints_offset": np.array(offsets, np.int64)}


def frustum_mesh(P: np.ndarray, size: tuple[int, int], depth: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera drawn as a pyramid: its centre and the four image corners back-projected to
    ``depth`` (world units). P: (3, 4); size: (width, height). -> vertices (5, 3), triangles (4, 3)."""
    w, h = size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    vertices = np.vstack([camera_center(P), backproject(P, corners, depth)])
    return vertices, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])


def _cameras_json(recon: Reconstruction, lenses: list | None = None, unit: str | None = None) -> dict[str, Any]:
    images = []
    for i, v in enumerate(recon.views):
        w, h = v.image_size
        entry: dict[str, Any] = {"name": v.name, "width": int(w), "height": int(h), "registered": v.registered,
                                 "status": v.status}
        if recon.rig is not None:  # a rig walk: views 2s, 2s + 1 are station s's left and right images
            entry.update(station=i // 2, side="right" if i % 2 else "left")
        if v.registered:
            K, R, t = Camera(v.P_input).krt
            entry.update(P=v.P_input.tolist(), K=K.tolist(), R=R.tolist(), t=t.tolist(),
                         center=v.center.tolist())
            if v.rotated_180:
                entry["rotated_180"] = True
            entry["reliable"] = bool(v.reliable)
            if not v.reliable:
                entry["flag_reason"] = v.flag_reason
            if v.uncertainty is not None:
                entry["uncertainty"] = v.uncertainty.summary()
        lens = lenses[lens_index(i, recon.rig is not None)] if lenses else None
        if lens is not None:
            # P is for the undistorted image: a photo's pixel is K_lens distort(K_lens^-1 pixel)
            entry.update(distortion=lens.distortion.tolist(), distortion_K=np.asarray(lens.K).tolist())
        images.append(entry)
    out = {"format_version": FORMAT_VERSION,
           "units": "those of the calibration (the pattern's coordinates): the model is metric in them",
           "convention": "P maps world (pattern frame) to pixels; pixel (0,0) = centre of the top-left pixel; "
                         "R, t are cam_from_world; uncertainty: 1-sigma of the centre along the camera's axes "
                         "(x right, y down, z forward, in the model's unit) and of its rotation about them "
                         "(degrees); reliable false: the run cannot vouch for the camera (flag_reason)",
           "images": images}
    if unit:  # the calibration named it (calib.json "unit")
        out["unit"] = unit
    return out


def write_result(recon: Reconstruction, report: dict[str, Any] | None, out_dir: str | Path,
                 cfg: Config = Config(), lenses: list | None = None) -> dict[str, Path]:
    """Write the result folder (each file atomically); returns {what: path}; ``report`` gains
    "exported_points" and "far_points_dropped" (far outliers left out). lenses: the
    calibration's two lenses (image 0 through the first, every later image through the second)
    when the run worked on undistorted images."""
    out = Path(out_dir)
    ids = exported_points(recon, cfg.export.far_point_factor)
    tracks = tracks_arrays(recon, ids)
    counts = np.bincount(tracks["obs_point"], minlength=len(ids))
    views = _views_per_point(tracks, len(ids))
    unit = report.get("unit") if isinstance(report, dict) else None
    written = {"cameras": write_json(out / "cameras.json", _cameras_json(recon, lenses, unit))}
    with atomic_path(out / "tracks.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **tracks)
    written["tracks"] = out / "tracks.npz"
    written["sparse"] = write_ply(out / "sparse.ply", tracks["point_xyz"], tracks["point_rgb"],
                                  {"error": tracks["point_error"].astype(np.float32),
                                   "track_length": counts.astype(np.int32), "n_views": views.astype(np.int32)})
    written["cameras_ply"] = _write_cameras_ply(recon, out / "cameras.ply", tracks["point_xyz"])
    if report is not None:  # the caller's report gains what was written, so what it prints matches the files
        report.update(format_version=FORMAT_VERSION, exported_points=int(len(ids)),
                      far_points_dropped=int(np.sum(recon.alive & (recon.track_lengths() >= 2)) - len(ids)))
        written["report"] = write_json(out / "report.json", report)
    return written


def _views_per_point(tracks: dict[str, np.ndarray], n_points: int) -> np.ndarray:
    return np.bincount(distinct_pair_firsts(tracks["obs_point"], tracks["obs_image"]), minlength=n_points)


def _write_cameras_ply(recon: Reconstruction, path: Path, points: np.ndarray) -> Path:
    """One frustum per registered camera, a tenth of the cameras' median distance to the scene
    deep; the calibrated pair orange, the walk blue."""
    reg = recon.registered_views
    centre = np.median(points, axis=0) if len(points) else np.zeros(3)
    depth = 0.1 * _camera_distance(recon, centre) if reg else 1.0
    vertices, faces, colours = [], [], []
    for n, v in enumerate(reg):
        view = recon.views[v]
        verts, tris = frustum_mesh(view.P_input, view.image_size, depth)
        vertices.append(verts)
        faces.append(tris + 5 * n)
        colours.append(np.tile([255, 140, 0] if v < 2 else [40, 110, 255], (5, 1)))
    if not reg:
        return write_ply(path, np.zeros((0, 3)), None, faces=np.zeros((0, 3)))
    return write_ply(path, np.vstack(vertices), np.vstack(colours).astype(np.uint8), faces=np.vstack(faces))
