"""A camera and its lens from views of a 3D pattern: the paper's normalised DLT per view, then
the maximum-likelihood estimate (Levenberg-Marquardt on the reprojection error) of one set of
intrinsics, one lens (OpenCV's radial k1, k2 [, k3] and tangential p1, p2 on K's pixels) and a
pose per view.

One view pins the lens only where the pattern was in the frame; more views of the pattern by
the same camera, the pattern elsewhere in the frame, pin it over the whole frame (the lens is
per physical camera). The first view is the stereo pair's: its pose is the camera's P.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.calibration.config import camera_problems
from stereoseed.geometry.camera import Camera
from stereoseed.estimators.calibration import check_correspondences, dlt_projection
from stereoseed.geometry.projection import compose_projection, depths
from stereoseed.errors import StereoseedError
from stereoseed.io.image_header import recorded_image_size
from stereoseed.io.nesting import read_bounded_text
from stereoseed.io.files import atomic_path
from stereoseed.geometry.lens import lens_coefficients, project_distorted

__all__ = ["LensCalibration", "Lens", "calibrate_lens", "read_lenses", "read_opencv_camera",
           "write_opencv_camera"]

# a view whose pattern points reproject worse than this is reported: pixels typed or detected with
# care reproject within a few pixels, mismatched or reordered ones by ~100 px
WARN_RMS_PX = 5.0


@dataclass
class LensCalibration:
    """K (3, 3), zero skew; distortion (5,) k1, k2, p1, p2, k3 (OpenCV's order); per view R
    (3, 3), t (3,), the RMS reprojection error (px) and the number of points. ``P`` is the first
    view's camera K [R | t], for undistorted pixels."""

    K: np.ndarray
    distortion: np.ndarray
    R: list[np.ndarray]
    t: list[np.ndarray]
    rms_px: list[float]
    n_points: list[int]
    image_size: tuple[int, int] | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def P(self) -> np.ndarray:
        return compose_projection(self.K, self.R[0], self.t[0])

    def to_dict(self) -> dict[str, Any]:
        """The calib.json entry of the camera (the pair's view)."""
        out = {"P": self.P.tolist(), "K": self.K.tolist(), "R": self.R[0].tolist(), "t": self.t[0].tolist(),
               "distortion": self.distortion.tolist(), "rms_px": self.rms_px[0], "n_points": self.n_points[0],
               "lens_views": len(self.R), "lens_views_rms_px": self.rms_px}
        if self.image_size is not None:
            out["image_size"] = list(self.image_size)
        return out


def _split(p: np.ndarray, n_views: int, n_lens: int, fixed: tuple | None) -> tuple:
    """K (3, 3), the lens (5,) and the poses (n_views, 6) (rotation vector, translation) of the
    parameters p: fx, fy, cx, cy and n_lens lens terms first unless ``fixed`` = (K, lens)."""
    if fixed is not None:
        return fixed[0], fixed[1], p.reshape(n_views, 6)
    fx, fy, cx, cy = p[:4]
    d = np.zeros(5)
    d[:n_lens] = p[4:4 + n_lens]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), d, p[4 + n_lens:].reshape(n_views, 6)


def _unpack(p: np.ndarray, n_views: int, n_lens: int, fixed: tuple | None) -> tuple:
    """K, the lens, and per view R (3, 3) and t (3,) of the parameters p (:func:`_split`)."""
    K, d, poses = _split(p, n_views, n_lens, fixed)
    return K, d, [cv2.Rodrigues(v[:3])[0] for v in poses], [v[3:] for v in poses]


def _jacobian(p: np.ndarray, views: list[tuple[np.ndarray, np.ndarray]], n_lens: int, fixed: tuple | None
              ) -> np.ndarray:
    """Jacobian (2 N_total, len(p)) of calibrate_lens's residuals (u, v per point, view after
    view) with respect to its parameters p (:func:`_split`), from ``cv2.projectPoints``: its
    model is :func:`project_distorted`'s and it returns the derivatives with respect to the
    rotation vector, the translation, fx, fy, cx, cy and k1, k2, p1, p2, k3, analytically (a
    finite-difference Jacobian cost a projection per parameter: 20 for two views)."""
    K, d, poses = _split(p, len(views), n_lens, fixed)
    n_intrinsics = len(p) - poses.size
    J = np.zeros((2 * sum(len(X) for X, _ in views), len(p)))
    row = 0
    for i, ((X, _), pose) in enumerate(zip(views, poses)):
        # columns of cv2's Jacobian: rvec (3), tvec (3), fx, fy, cx, cy, the 5 lens terms
        _, dp = cv2.projectPoints(X, pose[:3], pose[3:], K, d)
        # OpenCV leaves out K's skew s (a known K may have one): u = fx x + s y + cx and
        # v = fy y + cy for the distorted normalised (x, y), so du gains s / fy dv
        dp[0::2] += K[0, 1] / K[1, 1] * dp[1::2]
        rows = slice(row, row + 2 * len(X))
        if fixed is None:
            J[rows, :4] = dp[:, 6:10]
            J[rows, 4:n_intrinsics] = dp[:, 10:10 + n_lens]
        J[rows, n_intrinsics + 6 * i:n_intrinsics + 6 * i + 6] = dp[:, :6]
        row += 2 * len(X)
    return J


def calibrate_lens(views: list[tuple[np.ndarray, np.ndarray]], image_size: tuple[int, int] | None = None,
                   k3: bool = False, intrinsics: tuple[np.ndarray, np.ndarray] | None = None,
                   what: list[str] | None = None, max_rms_px: float | None = None) -> LensCalibration:
    """One camera and its lens from ``views``: [(pattern points (N, 3), their pixels (N, 2))],
    the stereo pair's view first. ``k3``: estimate the third radial term too (wide lenses);
    ``intrinsics``: (K, distortion) known already (an OpenCV calibration file): only the poses
    are estimated. ``what``: a name per view for the messages. A view reprojecting worse than
    ``WARN_RMS_PX`` is reported in ``warnings``, and refused above ``max_rms_px`` when given.
    Raises :class:`StereoseedError` when the camera is no physical one
    (:func:`stereoseed.calibration.config.camera_problems`) or the pattern is behind it."""
    what = what or [f"view {i}" for i in range(len(views))]
    checked = [check_correspondences(X, x, what=w) for (X, x), w in zip(views, what)]
    # a first guess per view: the normalised DLT, its K shared (zero skew) and its pose
    starts = [Camera(dlt_projection(X, x)).krt for X, x in checked]
    n_lens = 5 if k3 else 4
    if intrinsics is None:
        K0 = np.mean([K for K, _, _ in starts], axis=0)
        p0 = [K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]] + [0.0] * n_lens
        fixed = None
    else:
        fixed = (np.asarray(intrinsics[0], np.float64), lens_coefficients(intrinsics[1]))
        p0 = []
    for (K, R, t), (X, x) in zip(starts, checked):
        if fixed is not None:  # the pose that the known intrinsics give the DLT's rays
            t = np.linalg.solve(fixed[0], K @ t)
        p0 += list(cv2.Rodrigues(R)[0].ravel()) + list(t)

    def residuals(p: np.ndarray) -> np.ndarray:
        K, d, Rs, ts = _unpack(p, len(checked), n_lens, fixed)
        return np.concatenate([(project_distorted(K, R, t, d, X) - x).ravel() for (X, x), R, t in zip(checked, Rs, ts)])

    from scipy.optimize import least_squares  # here: a reconstruction that only reads a lens need not load it

    sol = least_squares(residuals, np.asarray(p0, np.float64), jac=lambda p: _jacobian(p, checked, n_lens, fixed),
                        method="lm", x_scale="jac", max_nfev=2000)
    K, d, Rs, ts = _unpack(sol.x, len(checked), n_lens, fixed)
    rms, counts, warnings = [], [], []
    for (X, x), R, t, name in zip(checked, Rs, ts, what):
        r = project_distorted(K, R, t, d, X) - x
        rms.append(float(np.sqrt(np.mean(np.sum(r * r, axis=1)))))
        counts.append(len(X))
        if np.any(depths(compose_projection(K, R, t), X) <= 0):
            raise StereoseedError(f"{name}: pattern points would be behind the camera; are u and v swapped?")
        limit = WARN_RMS_PX if max_rms_px is None else min(WARN_RMS_PX, max_rms_px)
        if rms[-1] > limit:
            message = (f"{name}: the pattern points reproject with {rms[-1]:.1f} px RMS; are the pixels those of these "
                       f"points, in the same order, and every view of this camera?")
            if max_rms_px is not None and rms[-1] > max_rms_px:
                raise StereoseedError(f"{message} (--max-rms {max_rms_px:g})")
            warnings.append(message)
    if intrinsics is None:
        problems = camera_problems(K, d, image_size)
        if problems:
            raise StereoseedError(f"{what[0]}: refused, no physical camera: {'; '.join(problems)}; the points do not "
                                  "determine it (more points, over more of the frame and at more depths, or --lens off)")
    return LensCalibration(K, d, Rs, ts, rms, counts, image_size, warnings)


@dataclass(frozen=True)
class Lens:
    """A camera's lens as calibrated: the distortion (5,) k1, k2, p1, p2, k3 on the pixels of K
    (3, 3), for images of ``image_size`` (width, height) or None when not recorded."""

    K: np.ndarray
    distortion: np.ndarray
    image_size: tuple[int, int] | None = None


def read_lenses(path: str | Path) -> list[Lens | None]:
    """The lens of each camera of a calib.json (None where it carries no "distortion": a
    hand-written calib.json, a Middlebury par file or a COLMAP model means no distortion).
    The file is expected to have passed :func:`stereoseed.io.files.read_calibration` already."""
    path = Path(path)
    if path.is_dir():
        return [None, None]
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
        cameras = data["cameras"] if isinstance(data, dict) else None
    except (OSError, ValueError, UnicodeDecodeError, KeyError):
        return [None, None]  # a par file: no lens
    lenses: list[Lens | None] = []
    for i, cam in enumerate(cameras[:2] if isinstance(cameras, list) else []):
        d = cam.get("distortion") if isinstance(cam, dict) else None
        if d is None:
            lenses.append(None)
            continue
        try:
            d = np.asarray(d, np.float64).reshape(-1)
            K = np.asarray(cam["K"], np.float64).reshape(3, 3) if "K" in cam else Camera(
                np.asarray(cam["P"], np.float64)).krt[0]
        except (ValueError, TypeError, KeyError):
            raise StereoseedError(f"{path}: camera {i}: 'distortion' needs 4 or 5 numbers (k1 k2 p1 p2 [k3]) and 'K' "
                                  f"a 3x3 matrix") from None
        if d.size not in (4, 5) or not np.all(np.isfinite(d)) or not np.all(np.isfinite(K)):
            raise StereoseedError(f"{path}: camera {i}: 'distortion' must be 4 or 5 finite numbers (k1 k2 p1 p2 [k3]), "
                                  f"got {d.size}")
        _refuse_no_camera(K, f"{path}: camera {i}: K")
        size = recorded_image_size(cam["image_size"], f"{path}: camera {i}: image_size") if "image_size" in cam else None
        lenses.append(Lens(K, lens_coefficients(d), size))
    return lenses + [None] * (2 - len(lenses))


# a K decomposed from P holds rounding where an exact one holds zeros: K[1, 0] may be this much of fy
_K_ROUNDING = 1e-9


def _refuse_no_camera(K: np.ndarray, where: str) -> None:
    """Refuse a K (3, 3) that is no camera's: its images would be undistorted into nothing (a zero
    K made every image black, later said as "no interest points")."""
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])
            and abs(K[1, 0]) <= _K_ROUNDING * K[1, 1]):
        raise StereoseedError(f"{where} {np.round(K, 3).tolist()} is no camera (it needs positive finite focal "
                              f"lengths fx, fy on the diagonal and a last row 0 0 1)")


def read_opencv_camera(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    """(K (3, 3), distortion (5,), image size (width, height) or None) from an OpenCV calibration
    file (cv::FileStorage YAML, XML or JSON with ``camera_matrix`` and ``distortion_coefficients``,
    as ``stereoseed intrinsics`` and OpenCV's samples write it). Anything else (not a FileStorage
    file, a matrix that is no camera, coefficients that are not finite) is refused in one line
    naming the file."""
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: intrinsics file not found")
    hint = ("give a YAML/XML/JSON written by cv::FileStorage (e.g. stereoseed intrinsics) with camera_matrix and "
            "distortion_coefficients")
    try:
        head = path.read_bytes()[:4096]
    except OSError as e:
        raise StereoseedError(f"{path}: cannot be read ({e.strerror}); {hint}") from None
    if not head.strip():
        raise StereoseedError(f"{path}: empty file; {hint}")
    if b"\0" in head or head.startswith(b"\x89PNG"):
        raise StereoseedError(f"{path}: a binary file, not an OpenCV calibration file; {hint}")
    try:  # bounded before OpenCV's parser, which recurses per level and crashes on a deeply nested file
        read_bounded_text(path, "calibration file", hint, encoding="latin-1")
    except OSError as e:
        raise StereoseedError(f"{path}: cannot be read ({e.strerror}); {hint}") from None
    try:  # OpenCV's parser reports a malformed file as cv2.error, or as a SystemError around it
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise StereoseedError(f"{path}: not an OpenCV calibration file; {hint}")
        K, d = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        width, height = (fs.getNode(k).real() if not fs.getNode(k).empty() else 0.0 for k in ("image_width", "image_height"))
        fs.release()
    except (cv2.error, SystemError, ValueError) as e:
        cause = e.__cause__ or e.__context__ or e  # the SystemError wraps the parser's cv2.error
        found = re.search(r"error: \((-?\d+):([^)]*)\).*?'[^']*?(\(\d+\))?: ?([^']*)'", str(cause))
        detail = (f"{found.group(2)}{' at line ' + found.group(3).strip('()') if found.group(3) else ''}: "
                  f"{found.group(4)}"[:80] if found else "OpenCV's parser refused it")
        raise StereoseedError(f"{path}: not a readable OpenCV calibration file ({detail}); {hint}") from None
    if K is None or K.shape != (3, 3) or d is None or d.size < 4:
        raise StereoseedError(f"{path}: needs camera_matrix (3x3) and distortion_coefficients (k1 k2 p1 p2 [k3 ...]); "
                              f"{hint}")
    K, d = np.asarray(K, np.float64), np.asarray(d, np.float64).reshape(-1)
    _refuse_no_camera(K, f"{path}: camera_matrix")
    if not np.all(np.isfinite(d)):
        raise StereoseedError(f"{path}: distortion_coefficients hold NaN or infinite values")
    if d.size > 5 and np.any(d[5:] != 0):
        raise StereoseedError(f"{path}: distortion terms beyond k3 (the rational or thin-prism model) are not "
                              f"modelled; calibrate with k1 k2 p1 p2 [k3] only")
    size = None if width == 0 and height == 0 else recorded_image_size((width, height), f"{path}: image_width, image_height")
    return K, lens_coefficients(d[:5]), size


def write_opencv_camera(path: str | Path, K: np.ndarray, distortion: np.ndarray, size: tuple[int, int],
                        rms_px: float, views: list[tuple[str, float]] | None = None) -> Path:
    """Write the camera as OpenCV's calibration samples do (cv::FileStorage; YAML, XML or JSON by
    the extension): camera_matrix, distortion_coefficients (1x5), image_width, image_height,
    avg_reprojection_error and, per view, its name and RMS (per_view_reprojection_errors).
    :func:`read_opencv_camera` and ``calibrate --intrinsics1/2`` read it back."""
    path = Path(path)
    if path.suffix.lower() not in (".yaml", ".yml", ".xml", ".json"):
        raise StereoseedError(f"{path}: give a .yaml, .yml, .xml or .json file to write the camera into")
    with atomic_path(path) as tmp:  # its name ends with path's extension, by which FileStorage picks the format
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(size[0]))
        fs.write("image_height", int(size[1]))
        fs.write("camera_matrix", np.asarray(K, np.float64))
        fs.write("distortion_coefficients", np.asarray(distortion, np.float64).reshape(1, -1))
        fs.write("avg_reprojection_error", float(rms_px))
        if views:
            fs.write("per_view_reprojection_errors", np.array([r for _, r in views], np.float64).reshape(-1, 1))
            fs.startWriteStruct("views", cv2.FileNode_SEQ)
            for name, _ in views:
                fs.write("", str(name))
            fs.endWriteStruct()
        fs.release()
    return path
