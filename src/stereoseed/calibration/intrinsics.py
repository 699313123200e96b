"""Zhang's method: a camera's intrinsics from views of flat boards, in closed form.

Each face of a target is a flat board: a view of it is a homography H from the face's plane
(metric coordinates, mm) to the image, H ~ K [r1 r2 t]. Its two constraints on the image of the
absolute conic B = K^-T K^-1 (r1 and r2 orthonormal: h1' B h2 = 0, h1' B h1 = h2' B h2) from
several views give B, hence K (Zhang, "A flexible new technique for camera calibration", PAMI
2000), here with zero skew. Then each view's pose follows from H and K. This is the start of
:mod:`stereoseed.calibration.refine_target`'s estimate, for a flat board and a 3D target alike:
every face is a board, so the intrinsics never depend on how well the faces were assembled.

With fewer than three boards' views (or a closed form that is no camera: a principal point
outside the frame, a negative focal length) the principal point is taken at the image's centre
and only the focal lengths solved for, as OpenCV's ``initIntrinsicParams2D`` does.
"""
from __future__ import annotations

from typing import Any

import logging

import numpy as np

from stereoseed.calibration.target import Face
from stereoseed.estimators.calibration import normalization_2d

log = logging.getLogger(__name__)

__all__ = ["shared_face_boards", "face_frame", "plane_coordinates", "homography", "zhang_intrinsics", "pose_from_homography",
           "MIN_HOMOGRAPHY_CORNERS"]

# A board's view enters the closed form with at least this many corners spread over two
# directions: 4 give an exact homography with no check of it, 8 over-determine it twice.
MIN_HOMOGRAPHY_CORNERS = 8
# the corners' spread across their main direction / along it: below this they lie on a line
# (a row of a board), which fixes no homography
_COLLINEAR_RATIO = 0.05
# the full closed form needs this many boards' views (2 constraints each on 4 unknowns and a
# scale); with fewer, or when its answer is no camera, the principal point is the frame's centre
_MIN_ZHANG_VIEWS = 3
_MAX_INIT_ASPECT = 0.25  # |fy / fx - 1| of a closed-form answer beyond this: no camera, fall back


def face_frame(face: Face) -> tuple[np.ndarray, np.ndarray]:
    """The face's plane as an orthonormal frame (origin O (3,), F (3, 3) columns e1 e2 e3: e1
    along u_axis, e2 in the plane, e3 = e1 x e2): a point X of the plane is O + F (a, b, 0)."""
    e1 = face.u_axis / np.linalg.norm(face.u_axis)
    v = face.v_axis - (face.v_axis @ e1) * e1
    e2 = v / np.linalg.norm(v)
    return face.origin.copy(), np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def plane_coordinates(face: Face, points3d: np.ndarray) -> np.ndarray:
    """(N, 2) metric coordinates (a, b) of the face's points (N, 3) in :func:`face_frame`."""
    O, F = face_frame(face)
    return (np.asarray(points3d, np.float64) - O) @ F[:, :2]


def homography(plane: np.ndarray, pixels: np.ndarray) -> np.ndarray | None:
    """The homography (3, 3) taking plane coordinates (N, 2) to pixels (N, 2): normalised DLT
    (HZ algorithm 4.2). None for fewer than 4 points or points on a line."""
    plane, pixels = np.asarray(plane, np.float64), np.asarray(pixels, np.float64)
    if len(plane) < 4:
        return None
    sv = np.linalg.svd(plane - plane.mean(0), compute_uv=False)
    if sv[1] < _COLLINEAR_RATIO * sv[0]:
        return None
    Ta, Tb = normalization_2d(plane), normalization_2d(pixels)
    a = np.c_[plane, np.ones(len(plane))] @ Ta.T
    b = np.c_[pixels, np.ones(len(pixels))] @ Tb.T
    A = np.zeros((2 * len(a), 9))
    A[0::2, 0:3], A[0::2, 6:9] = a, -b[:, :1] * a
    A[1::2, 3:6], A[1::2, 6:9] = a, -b[:, 1:2] * a
    H = np.linalg.solve(Tb, np.linalg.svd(A)[2][-1].reshape(3, 3) @ Ta)
    return H / np.linalg.norm(H)


def _plausible(K: np.ndarray, size: tuple[int, int]) -> bool:
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return bool(np.all(np.isfinite(K)) and fx > 0 and fy > 0 and abs(fy / fx - 1) <= _MAX_INIT_ASPECT
                and 0 <= cx <= size[0] and 0 <= cy <= size[1])


def _closed_form(Hs: list[np.ndarray]) -> np.ndarray | None:
    """K from B = K^-T K^-1 with zero skew: b = (B11, B22, B13, B23, B33) from V b = 0."""
    rows = []
    for H in Hs:
        h1, h2 = H[:, 0], H[:, 1]

        def v(p: np.ndarray, q: np.ndarray) -> np.ndarray:
            return np.array([p[0] * q[0], p[1] * q[1], p[0] * q[2] + p[2] * q[0], p[1] * q[2] + p[2] * q[1],
                             p[2] * q[2]])

        rows += [v(h1, h2), v(h1, h1) - v(h2, h2)]
    B11, B22, B13, B23, B33 = np.linalg.svd(np.array(rows))[2][-1]
    if B11 * B22 <= 0:
        return None
    cx, cy = -B13 / B11, -B23 / B22
    lam = B33 - cx * cx * B11 - cy * cy * B22
    if lam / B11 <= 0 or lam / B22 <= 0:
        return None
    return np.array([[np.sqrt(lam / B11), 0.0, cx], [0.0, np.sqrt(lam / B22), cy], [0.0, 0.0, 1.0]])


def _focal_only(Hs: list[np.ndarray], centre: np.ndarray) -> np.ndarray | None:
    """K with its principal point at ``centre``: the constraints are then linear in 1 / fx^2
    and 1 / fy^2 (B33 = 1), or in one 1 / f^2 when the two are not separately determined."""
    A, y = [], []
    for H in Hs:
        h1, h2 = H[:, 0], H[:, 1]
        A += [[h1[0] * h2[0], h1[1] * h2[1]], [h1[0] ** 2 - h2[0] ** 2, h1[1] ** 2 - h2[1] ** 2]]
        y += [-h1[2] * h2[2], -(h1[2] ** 2 - h2[2] ** 2)]
    A, y = np.array(A), np.array(y)
    sol = np.linalg.lstsq(A, y, rcond=None)[0]
    if not np.all(sol > 0):  # fx and fy not separately determined: square pixels
        s = np.linalg.lstsq(A.sum(axis=1, keepdims=True), y, rcond=None)[0]
        if not s[0] > 0:
            return None
        sol = np.array([s[0], s[0]])
    fx, fy = 1.0 / np.sqrt(sol)
    return np.array([[fx, 0.0, centre[0]], [0.0, fy, centre[1]], [0.0, 0.0, 1.0]])


def zhang_intrinsics(Hs: list[np.ndarray], size: tuple[int, int]) -> np.ndarray | None:
    """K (3, 3), zero skew, from homographies (plane mm -> pixels) of flat boards seen by one
    camera with images of ``size`` (width, height). None when nothing fits."""
    if not Hs:
        return None
    # pixels scaled to about 1 around the frame's centre: B's entries then have like magnitudes
    centre = np.array([(size[0] - 1) / 2.0, (size[1] - 1) / 2.0])
    s = 1.0 / max(size)
    N = np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])
    Hn = [N @ H / np.linalg.norm(N @ H) for H in Hs]
    if len(Hs) >= _MIN_ZHANG_VIEWS:
        K = _closed_form(Hn)
        if K is not None:
            K = np.linalg.solve(N, K)
            if _plausible(K, size):
                return K / K[2, 2]
            log.debug("Zhang's closed form gave no camera (%s); principal point at the centre", np.round(K, 1).tolist())
    K = _focal_only(Hn, np.zeros(2))
    return None if K is None else np.linalg.solve(N, K) / np.linalg.solve(N, K)[2, 2]


def pose_from_homography(H: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the camera from the board's plane frame, H ~ K [r1 r2 t], R the nearest
    rotation (SVD), the board in front of the camera."""
    A = np.linalg.solve(K, H)
    scale = 2.0 / (np.linalg.norm(A[:, 0]) + np.linalg.norm(A[:, 1]))
    if A[2, 2] * scale < 0:  # the plane's origin behind the camera: the other sign
        scale = -scale
    r1, r2, t = A[:, 0] * scale, A[:, 1] * scale, A[:, 2] * scale
    U, _, Vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=1))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R, t


def shared_face_boards(target: Any, pairs: Any, min_common: int = 12
                       ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The corners two cameras saw of the same face in the same shot, each face a flat board of
    its own, as OpenCV's ``stereoCalibrate`` takes them: (object points (N, 3) float32 on the
    face's plane, camera 1's pixels (N, 2), camera 2's), one entry per face and shot with at least
    ``min_common`` corners in both. ``pairs``: (camera 1's detections, camera 2's) by shot."""
    obj, img1, img2 = [], [], []
    for d1, d2 in zip(*pairs):
        for f in set(d1.faces_found) & set(d2.faces_found):
            common, i1, i2 = np.intersect1d(d1.ids[d1.face == f], d2.ids[d2.face == f], return_indices=True)
            if len(common) >= min_common:
                m1 = np.flatnonzero(d1.face == f)[i1]
                plane = plane_coordinates(target.faces[f], d1.points3d[m1])
                obj.append(np.c_[plane, np.zeros(len(m1))].astype(np.float32))
                img1.append(d1.pixels[m1].astype(np.float32))
                img2.append(d2.pixels[np.flatnonzero(d2.face == f)[i2]].astype(np.float32))
    return obj, img1, img2
