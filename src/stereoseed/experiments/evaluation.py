"""Measures against ground truth: the paper's eq. 13 (3D RMS) and eq. 14, camera errors, and the
exact correspondences of a synthetic scene (to measure the reconstruction chain by itself)."""
from __future__ import annotations

from typing import Any

import numpy as np

from stereoseed.geometry.camera import Camera
from stereoseed.arrays import unique
from stereoseed.geometry.projection import camera_center, project, rotation_angle_deg
from stereoseed.features.harris import Features
from stereoseed.matching.containers import Matches
from stereoseed.estimators.triangulation import triangulate_tracks

__all__ = ["rms_3d", "camera_errors", "reconstruct_corners", "corners_from_exact_pixels", "TrueCorrespondences",
           "surface_distance"]


def rms_3d(points: np.ndarray, truth: np.ndarray) -> float:
    """Paper eq. 13: sqrt(mean ||M_i - M_i^c||^2), no alignment. (N, 3), (N, 3) -> metres."""
    d = np.asarray(points) - np.asarray(truth)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def camera_errors(Ps_est: list[np.ndarray | None], Ps_true: list[np.ndarray]) -> dict[str, list]:
    """Per image: centre error (m) and rotation error (degrees); None where unregistered."""
    centre, rot = [], []
    for Pe, Pt in zip(Ps_est, Ps_true):
        if Pe is None:
            centre.append(None)
            rot.append(None)
            continue
        centre.append(float(np.linalg.norm(camera_center(Pe) - camera_center(Pt))))
        rot.append(rotation_angle_deg(Camera(Pe).R, Camera(Pt).R))
    return {"center_m": centre, "rotation_deg": rot}


def reconstruct_corners(Ps_est: list[np.ndarray | None], images_features: list[Features | None],
                        corners: np.ndarray, Ps_true: list[np.ndarray], visibility: list[np.ndarray],
                        radius_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct known pattern corners the way the pipeline sees them: in every registered
    image, the detected interest point nearest the corner's true projection (within radius_px)
    is its image; the corner is triangulated from all of them with the *estimated* cameras.

    Returns (points (K, 3), indices (K,) of the corners seen in >= 2 images).
    """
    P_obs, xy, idx = [], [], []
    for Pe, feats, Pt, vis in zip(Ps_est, images_features, Ps_true, visibility):
        if Pe is None or feats is None or len(feats.points) == 0:
            continue
        proj = project(Pt, corners)
        d = np.linalg.norm(feats.points[None, :, :] - proj[:, None, :], axis=2)
        nearest = np.argmin(d, axis=1)
        ok = vis & (d[np.arange(len(corners)), nearest] <= radius_px)
        for c in np.flatnonzero(ok):
            P_obs.append(Pe)
            xy.append(feats.points[nearest[c]])
            idx.append(c)
    return _triangulate_corners(P_obs, np.array(xy).reshape(-1, 2), np.array(idx, np.int64))


def _triangulate_corners(P_obs: list[np.ndarray], xy: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners from their observations (camera (3, 4), pixel (2,), corner index), each over all
    its views: (points (K, 3), indices (K,)); corners seen once are left out."""
    if len(idx) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    seen = unique(idx)
    X = triangulate_tracks(np.stack(P_obs), xy, np.searchsorted(seen, idx), len(seen))
    ok = np.all(np.isfinite(X), axis=1)  # NaN: seen in fewer than two views
    return X[ok], seen[ok]


def corners_from_exact_pixels(Ps_est: list[np.ndarray | None], corners: np.ndarray, Ps_true: list[np.ndarray],
                              visibility: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The pattern corners triangulated from their exact pixels (true projections) with the
    *estimated* cameras: eq. 13 without the detector's share, i.e. what the cameras alone cost.
    :func:`reconstruct_corners` is the same with the detected interest points.

    Returns (points (K, 3), indices (K,) of the corners seen in >= 2 registered images).
    """
    P_obs, xy, idx = [], [], []
    for Pe, Pt, vis in zip(Ps_est, Ps_true, visibility):
        if Pe is None:
            continue
        seen = np.flatnonzero(vis)
        P_obs += [Pe] * len(seen)
        xy.append(project(Pt, corners[seen]))
        idx.append(seen)
    if not idx:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return _triangulate_corners(P_obs, np.concatenate(xy), np.concatenate(idx))


class TrueCorrespondences:
    """Exact correspondences of a synthetic scene (plus Gaussian pixel noise), a drop-in for the
    pipeline's Harris + ZNCC source: the same chain then runs on perfect matches, which measures
    the method's own limit.

    scene: a :class:`stereoseed.synthetic.scene.SyntheticScene`; n_points: surface points sampled
    once; max_matches: matches returned per pair (the paper's chains keep ~300).
    """

    def __init__(self, scene: Any, n_points: int = 4000, noise_px: float = 0.1, max_matches: int = 300,
                 seed: int = 0, include_ground: bool = True):
        rng = np.random.default_rng(seed)
        self.scene = scene
        self.points, _ = scene.sample_surface_points(n_points, rng, include_ground=include_ground)
        self.max_matches = max_matches
        self.seed = seed
        self._ids: dict[int, np.ndarray] = {}
        self._noise = noise_px

    def features(self, index: int, image: np.ndarray) -> Features:
        vis = self.scene.is_visible(index, self.points, margin=8.0)
        ids = np.flatnonzero(vis)
        rng = np.random.default_rng([self.seed, index])
        # pinhole pixels: with a lens scene these are the pixels of the undistorted images the
        # pipeline works on (it undistorts what it reads)
        xy = project(self.scene.P[index], self.points[ids]) + rng.normal(0, self._noise, (len(ids), 2))
        self._ids[index] = ids
        n = len(ids)
        return Features(points=xy, desc=np.zeros((n, 1), np.float32), valid=np.ones(n, bool),
                        response=np.ones(n), image_shape=image.shape[:2])

    def match(self, a: int, b: int, fa: Features, fb: Features, F: np.ndarray | None, image_width: int) -> Matches:
        common, ia, ib = np.intersect1d(self._ids[a], self._ids[b], return_indices=True)
        if len(common) > self.max_matches:
            keep = np.sort(np.random.default_rng([self.seed, a, b]).choice(len(common), self.max_matches, replace=False))
            ia, ib = ia[keep], ib[keep]
        return Matches(ia, ib, np.ones(len(ia)))

    def track(self, ref: int, target: int, f_ref: Features, ref_idx: np.ndarray, f_target: Features,
              predicted: np.ndarray, max_shift_px: float) -> tuple[np.ndarray, np.ndarray]:
        """The exact (noisy) image in view ``target`` of the surface points behind ``ref_idx``."""
        ids = self._ids[ref]
        ref_idx = np.asarray(ref_idx)
        appended = ref_idx >= len(ids)
        if appended.any():  # features the pipeline added by tracking sit on an original one
            from scipy.spatial import cKDTree
            ref_idx = ref_idx.copy()
            ref_idx[appended] = cKDTree(f_ref.points[:len(ids)]).query(f_ref.points[ref_idx[appended]])[1]
        wanted = ids[ref_idx]
        order = np.argsort(self._ids[target])
        pos = np.clip(np.searchsorted(self._ids[target], wanted, sorter=order), 0, len(order) - 1)
        hit = self._ids[target][order[pos]] == wanted
        xy = f_target.points[order[pos]]
        ok = hit & (np.linalg.norm(xy - predicted, axis=1) <= max_shift_px)
        return xy, ok


def surface_distance(points: np.ndarray, half: float = 0.17, height: float = 0.44) -> np.ndarray:
    """Distance (m) of each point (N, 3) to the synthetic scene's surfaces: the box
    [-half, half]^2 x [0, height] and the ground plane z = 0."""
    centre_z = height / 2
    q = np.c_[np.abs(points[:, :2]) - half, np.abs(points[:, 2] - centre_z) - centre_z]
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return np.minimum(np.abs(outside + inside), np.abs(points[:, 2]))


def surface_normal(points: np.ndarray, half: float = 0.17, height: float = 0.44) -> np.ndarray:
    """Outward unit normal (N, 3) of the synthetic scene's surface nearest to each point (N, 3):
    a face of the box [-half, half]^2 x [0, height] or the ground plane z = 0 around it."""
    x, y, z = points.T
    over_box = (np.abs(x) <= half) & (np.abs(y) <= half)
    beside = (z >= 0) & (z <= height)
    dist = np.stack([np.where(over_box & (z > 0), np.inf, np.abs(z)),  # the ground, outside the box
                     np.where(beside, np.abs(x - half), np.inf), np.where(beside, np.abs(x + half), np.inf),
                     np.where(beside, np.abs(y - half), np.inf), np.where(beside, np.abs(y + half), np.inf),
                     np.where(over_box, np.abs(z - height), np.inf)], axis=1)
    faces = np.array([[0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    return faces[np.argmin(dist, axis=1)]
