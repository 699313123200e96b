"""A camera judged again once the walk has placed its neighbours (issue "Cameras you can trust",
consistency after the fact).

At its registration a camera was predicted from the motion before it (extrapolated); once the
views on both sides are placed, the camera between them is predicted far better (interpolated).
The motion prior's search around that prediction (:func:`stereoseed.sfm.motion_prior.hypotheses_near`)
gives cameras that compete with the one the run kept by the neighbours' points they explain
(:func:`stereoseed.sfm.motion_prior.explained_points`), as at registration. A rival standing
apart (``TrustConfig.ambiguity_shift`` of the depth) that explains clearly more
(``MotionPriorConfig.wider_search_margin`` times the points) contradicts the camera: on the
castle walked from its 11th image, 0016 was placed 3.7 m off on the wrong copy of the windows
(it explains 150 of its neighbours' points; a camera 3.7 m away, the true one, 275). Rivals
that explain nearly as much are no evidence here: a good camera has them too (2-5 % of the
depth away, on the castle and the dino).
"""
from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from stereoseed.config import Config
from stereoseed.geometry.projection import camera_center, depths
from stereoseed.sfm.flags import FlagKind
from stereoseed.sfm.motion_prior import described_points, explained_points, hypotheses_near
from stereoseed.sfm.reconstruction import Reconstruction
from stereoseed.sfm.refinement import CALIBRATED
from stereoseed.sfm.registration.base import Candidate, FoundBy, Resector

__all__ = ["contradicted_by_neighbours", "between"]

log = logging.getLogger(__name__)


def between(P_a: np.ndarray, P_b: np.ndarray, K: np.ndarray, t: float) -> np.ndarray:
    """The camera (3, 4) with intrinsics K (3, 3) a fraction ``t`` of the way from camera P_a to
    camera P_b (3, 4): its centre on the segment, its rotation on the shortest arc."""
    poses = []
    for P in (P_a, P_b):
        R = np.linalg.solve(K, P[:, :3])
        U, _, Vt = np.linalg.svd(R)  # the nearest rotation (P_a, P_b may carry other intrinsics)
        poses.append((U @ Vt * np.sign(np.linalg.det(U @ Vt)), camera_center(P)))
    R = Slerp([0.0, 1.0], Rotation.from_matrix([poses[0][0], poses[1][0]]))([t]).as_matrix()[0]
    C = (1.0 - t) * poses[0][1] + t * poses[1][1]
    return K @ np.hstack([R, -(R @ C)[:, None]])


def contradicted_by_neighbours(recon: Reconstruction, cfg: Config, doubted: set[int] = frozenset()) -> dict[int, str]:
    """{view: reason} of the registered views after the pair, not flagged at their registration
    nor in ``doubted``, whose camera a rival predicted from their neighbours contradicts (the
    module's rule). The neighbours: the nearest such views on either side (a wrong neighbour
    would predict wrong). A camera the epipolar chain placed is not judged again: its
    own two-view geometry placed it, where the others were predicted (a split chain competes
    with the motion prior at registration). Not on a rig walk (a station's two images are one
    body; their neighbours are each other)."""
    cfg = cfg.resolve()
    mp, tc = cfg.motion_prior, cfg.trust
    if recon.rig is not None:
        return {}
    sound = [v for v in recon.registered_views if not recon.views[v].registration_flag and v not in doubted]
    out = {}
    for k in (v for v in sound if v not in CALIBRATED):
        view = recon.views[k]
        a = max((v for v in sound if v < k), default=None)
        b = min((v for v in sound if v > k), default=None)
        if (a is None or b is None or view.found_by == FoundBy.EPIPOLAR_CHAIN or view.features is None
                or view.image_size is None):
            continue
        # their points, each described by its patch at its first observation in a or b
        pids, desc = described_points(recon, np.flatnonzero(np.isin(recon.obs_view, [a, b])
                                                             & recon.alive[recon.obs_point]), a)
        if len(pids) < cfg.resection.min_points:
            continue
        # the resection reads only the image's size: no pixels read again
        size_only = np.broadcast_to(np.zeros((), np.uint8), view.image_size[::-1])
        cand = Candidate(k, view.name, size_only, view.features, view.rotated_180)
        resect = Resector(recon, a, cand, cfg)
        cameras = [view.P]
        for hypotheses in hypotheses_near(recon, between(recon.views[a].P, recon.views[b].P, view.K, (k - a) / (b - a)),
                                          view.features, cfg, (pids, desc)):
            for hyp in hypotheses:
                if len(hyp) >= cfg.registration.min_chained_points:
                    found = resect(hyp.points3d, hyp.points2d, hyp.scores)
                    if not isinstance(found, str):
                        cameras.append(found[0].P)
        counts = explained_points(view.features, cameras, recon.points[pids], desc, mp.explain_px, mp.min_zncc)
        depth = float(np.median(depths(view.P, recon.points[pids])))
        centre = camera_center(view.P)
        rivals = [(int(n), float(np.linalg.norm(camera_center(P) - centre))) for n, P in zip(counts[1:], cameras[1:])]
        # clearly more, and at least a resection's worth (a count of 0 against 0 says nothing)
        rivals = [(n, d) for n, d in rivals if n >= max(mp.wider_search_margin * counts[0], cfg.resection.min_inliers)
                  and d > tc.ambiguity_shift * depth]
        if rivals:
            n, d = max(rivals)
            out[k] = (f"{FlagKind.CONTRADICTED}: a camera {d:.3g} away ({100 * d / depth:.1f} % of the scene's depth), "
                      f"found between {recon.views[a].name} and {recon.views[b].name}, explains {n} of their points, "
                      f"this one {int(counts[0])}")
    return out
