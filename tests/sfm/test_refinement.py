"""The global BA of a large model: the track subset it adjusts the cameras on."""
import numpy as np

from geometry_helpers import box_points, ring_camera
from stereoseed.geometry.projection import camera_center, project
from stereoseed.config import Config, PipelineConfig
from stereoseed.features.harris import Features
from stereoseed.scene.reconstruction import Reconstruction, View
from stereoseed.sfm.refinement import global_adjust, select_tracks


def _ring(rng, n_views=8, n_points=600, noise_px=0.2, seen=None):
    """A reconstruction of box points seen from a ring, 15 degrees apart, the moving camera's
    views drifted 1-2 cm; ``seen(view) -> (N,) bool`` picks the points each view observes
    (default: all). Returns (recon, true cameras, true points)."""
    X = box_points(rng, n_points)
    cams = [ring_camera(15.0 * i)[3] for i in range(n_views)]
    views = []
    for i, P in enumerate(cams):
        x = project(P, X) + rng.normal(0, noise_px, (len(X), 2))
        feats = Features(x, np.zeros((len(X), 1), np.float32), np.ones(len(X), bool), np.ones(len(X)), (480, 640))
        views.append(View(name=f"v{i}", features=feats, P=P.copy(), point_of_feature=np.full(len(X), -1, np.int64)))
    recon = Reconstruction(views)
    ids = recon.add_points(X + rng.normal(0, 0.003, X.shape), np.zeros((len(X), 3)))
    for i in range(n_views):
        keep = np.ones(len(X), bool) if seen is None else seen(i)
        recon.add_observations(i, np.flatnonzero(keep), ids[keep])
    for v in views[2:]:
        angle = float(np.degrees(np.arctan2(*camera_center(v.P)[1::-1])))
        v.P = ring_camera(angle + 0.6, distance=1.41)[3]
    return recon, cams, X


def _centre_errors(recon, cams):
    return np.array([np.linalg.norm(camera_center(v.P) - camera_center(P)) for v, P in zip(recon.views[2:], cams[2:])])


def test_select_tracks_keeps_the_longest_track_of_every_occupied_cell():
    rng = np.random.default_rng(1)
    # tracks of every length: point p is seen by views 0..(p mod 8), and always by 0 and 1
    recon, _, _ = _ring(rng, seen=lambda i: (np.arange(600) % 8 >= i) | (i < 2))
    cells = 4
    kept = set(select_tracks(recon, cells).tolist())
    length = recon.track_lengths()
    for v in recon.registered_views:
        rows = recon.obs_view == v
        xy = recon.observation_xy(rows)
        cell = np.floor((xy + 0.5) * cells / [640, 480]).astype(int).clip(0, cells - 1) @ [1, cells]
        points = recon.obs_point[rows]
        for c in np.unique(cell):
            in_cell = points[cell == c]
            best = length[in_cell].max()
            assert any(p in kept and length[p] == best for p in in_cell)  # one longest track of the cell kept
    assert len(kept) < 0.5 * len(recon.points)


def test_global_adjust_on_a_track_subset_stays_close_to_the_full_one():
    # the calibrated intrinsics held (a focal length per view trades against the depth here)
    cfg = Config(pipeline=PipelineConfig(mode="accurate", camera_model="fixed"))
    full, cams, _ = _ring(np.random.default_rng(2))
    opts = cfg.mapper_options()
    ba_full, _ = global_adjust(full, opts.bundle, opts.outliers, opts.pipeline.camera_model)
    subset, _, X = _ring(np.random.default_rng(2))
    drift = _centre_errors(subset, cams).max()
    subset_bundle = cfg.replace(bundle={"subset_above": 1.0, "subset_cells": 8}).bundle
    ba, _ = global_adjust(subset, subset_bundle, opts.outliers, opts.pipeline.camera_model)
    assert "subset_points" not in ba_full
    assert ba["subset_points"] < 0.3 * len(X) and ba["subset_points"] + ba["other_points"] == len(X)
    err_full, err_subset = _centre_errors(full, cams).max(), _centre_errors(subset, cams).max()
    # 1.5 cm of drift taken out by both; every view here sees every point, so the subset's
    # camera is as precise as its share of the points allows (0.2 px noise: 0.5 mm with all
    # 600 points, 1.5 mm with the ~115 kept)
    assert drift > 0.01 and err_full < 1e-3 and err_subset < 4 * err_full
    # the points the cameras were not adjusted on are refitted to them as well as the others
    assert ba["rms_after_px"] < 0.3 and subset.reprojection_summary()["rms_px"] < 0.3
