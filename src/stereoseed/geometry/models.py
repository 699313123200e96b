"""Camera models: how a projection matrix is parameterised for refinement and bundle adjustment.

A camera is K (intrinsics) + rotation vector (3) + translation (3). The models differ in which
intrinsics are free:

* ``free``      - the paper's 11-DOF camera: fx, fy, skew, cx, cy (5) + 6.
* ``zero-skew`` - square pixels and no skew, principal point free: f, cx, cy (3) + 6.
* ``focal``     - a zoom lens: only the focal length varies; aspect ratio, skew and principal
                  point are those of a reference camera (the calibrated second camera): 1 + 6.
* ``fixed``     - the reference camera's intrinsics, only the pose is estimated: 6 (a fallback
                  when the points are too flat for the focal length to be observable).
"""
from __future__ import annotations

import numpy as np

from stereoseed.geometry.camera_model import MODELS, N_INTRINSICS, CameraModel
from stereoseed.geometry.projection import compose_projection, decompose_projection



__all__ = ["CameraModel", "MODELS", "N_INTRINSICS", "n_params", "params_from_krt", "params_from_projection", "projections_from_params",
           "krt_from_params", "projection_from_params", "project_to_model", "projection_derivatives",
           "rotation_from_vector", "rotations_from_vectors", "Ks_from_intrinsics", "linear_K"]


def n_params(model: str) -> int:
    return _check(model).n_params


def _check(model: str) -> CameraModel:
    try:
        return CameraModel(model)
    except ValueError:
        raise ValueError(f"unknown camera model {model!r}; choose one of {', '.join(MODELS)}") from None


def _intrinsics_from_K(K: np.ndarray, model: str, reference_K: np.ndarray | None) -> np.ndarray:
    if model == CameraModel.FREE:
        return np.array([K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]])
    if model == CameraModel.ZERO_SKEW:
        return np.array([0.5 * (K[0, 0] + K[1, 1]), K[0, 2], K[1, 2]])
    ref = _require_reference(reference_K)
    if model == CameraModel.FIXED:
        return np.zeros(0)
    # least-squares focal that best reproduces K's fx, fy with the reference's aspect ratio
    aspect = ref[1, 1] / ref[0, 0]
    return np.array([(K[0, 0] + aspect * K[1, 1]) / (1.0 + aspect * aspect)])


def _require_reference(reference_K: np.ndarray | None) -> np.ndarray:
    if reference_K is None:
        raise ValueError("the 'focal' and 'fixed' camera models need the reference camera's K")
    return np.asarray(reference_K, dtype=np.float64)


def K_from_intrinsics(intr: np.ndarray, model: str, reference_K: np.ndarray | None) -> np.ndarray:
    """Build K (3, 3) from the model's intrinsic parameters."""
    return Ks_from_intrinsics(np.asarray(intr, np.float64)[None], model, reference_K)[0]


def Ks_from_intrinsics(intr: np.ndarray, model: str, reference_K: np.ndarray | None) -> np.ndarray:
    """K (B, 3, 3) of B intrinsic vectors (B, N_INTRINSICS[model]); reference_K (3, 3) or
    (B, 3, 3) for the "focal" and "fixed" models."""
    B = len(intr)
    if model in (CameraModel.FREE, CameraModel.ZERO_SKEW):
        K = np.zeros((B, 3, 3))
        if model == CameraModel.FREE:  # fx, fy, skew, cx, cy
            K[:, 0, 0], K[:, 1, 1], K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = intr[:, :5].T
        else:  # f, cx, cy
            K[:, 0, 0], K[:, 0, 2], K[:, 1, 2] = intr[:, :3].T
            K[:, 1, 1] = intr[:, 0]
        K[:, 2, 2] = 1.0
        return K
    K = np.broadcast_to(_require_reference(reference_K), (B, 3, 3)).copy()
    if model == CameraModel.FOCAL:  # the reference's 2x2 block scaled by f / f_ref
        scale = intr[:, 0] / K[:, 0, 0]
        K[:, 0, 0] *= scale
        K[:, 0, 1] *= scale
        K[:, 1, 1] *= scale
    return K


def params_from_krt(K: np.ndarray, R: np.ndarray, t: np.ndarray, model: str,
                    reference_K: np.ndarray | None = None) -> np.ndarray:
    """Parameter vector (n_params(model),) of a camera K, R, t under ``model``."""
    _check(model)
    rvec = rotation_vector(R)
    return np.concatenate([_intrinsics_from_K(K, model, reference_K), rvec, np.asarray(t, float).ravel()])


def params_from_projection(P: np.ndarray, model: str, reference_K: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray | None]:
    """(params, reference_K) for P (3, 4); a constrained model takes the closest K of its family."""
    return params_from_decomposition(*decompose_projection(P), model, reference_K), reference_K


def params_from_decomposition(K: np.ndarray, R: np.ndarray, t: np.ndarray, model: str,
                              reference_K: np.ndarray | None = None) -> np.ndarray:
    """The parameters of the camera K [R | t] (P's decomposition) under ``model``: a constrained
    model takes the closest K of its family and keeps the camera centre."""
    if model != CameraModel.FREE:
        # Re-express t for the constrained K so the camera centre is kept: t = -R C.
        C = -R.T @ t
        Kc = K_from_intrinsics(_intrinsics_from_K(K, model, reference_K), model, reference_K)
        return params_from_krt(Kc, R, -R @ C, model, reference_K)
    return params_from_krt(K, R, t, model, reference_K)


def rotation_from_vector(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, (3,) -> (3, 3)."""
    return rotations_from_vectors(np.asarray(rvec, np.float64)[None])[0]


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) (w, x, y, z) of the rotation R (3, 3), w >= 0 (COLMAP's order).

    Markley's method (J. Guidance 2008, what scipy's Rotation.from_matrix does): the quaternion
    is built from the largest of R's diagonal terms and its trace, so no square root or inverse
    cosine loses precision, near a half turn included."""
    R = np.asarray(R, np.float64)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    choice = int(np.argmax([R[0, 0], R[1, 1], R[2, 2], trace]))
    q = np.empty(4)  # (x, y, z, w) while it is built
    if choice < 3:
        i, j, k = choice, (choice + 1) % 3, (choice + 2) % 3
        q[i] = 1.0 - trace + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    else:
        q[:] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1.0 + trace
    q /= np.linalg.norm(q)
    return np.array([q[3], q[0], q[1], q[2]]) * (1.0 if q[3] >= 0 else -1.0)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) (axis times angle, angle in [0, pi]) of R (3, 3): the inverse of
    :func:`rotation_from_vector`, from the quaternion (precise at every angle)."""
    w, *v = quaternion_from_rotation(R)
    s = float(np.linalg.norm(v))
    angle = 2.0 * np.arctan2(s, w)
    return np.asarray(v) * (angle / s if s > 1e-300 else 2.0)


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of the quaternion q (4,) (w, x, y, z), normalised first. Raises
    ValueError for a zero or non-finite q (scipy's Rotation.from_quat does too)."""
    q = np.asarray(q, np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"{q.tolist()} is not a rotation's quaternion")
    w, x, y, z = q / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rotations_from_vectors(rvecs: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for B rotation vectors (B, 3) -> (B, 3, 3); written out because it runs
    in the BA's and the resection's loops, where scipy's Rotation object costs ten times more.
    First order below 1e-12 rad."""
    theta = np.sqrt(np.sum(rvecs ** 2, axis=1))
    turned = theta >= 1e-12
    k = np.where(turned[:, None], rvecs / np.where(turned, theta, 1.0)[:, None], rvecs)  # the axis, or the vector itself
    Kx = np.zeros((len(rvecs), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    sin = np.where(turned, np.sin(theta), 1.0)[:, None, None]
    one_minus_cos = np.where(turned, 1.0 - np.cos(theta), 0.0)[:, None, None]
    return np.eye(3) + sin * Kx + one_minus_cos * (Kx @ Kx)


def krt_from_params(params: np.ndarray, model: str, reference_K: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ni = N_INTRINSICS[_check(model)]
    K = K_from_intrinsics(params[:ni], model, reference_K)
    R = rotation_from_vector(np.asarray(params[ni:ni + 3], dtype=np.float64))
    return K, R, np.asarray(params[ni + 3:ni + 6], dtype=np.float64)


def projection_from_params(params: np.ndarray, model: str, reference_K: np.ndarray | None = None) -> np.ndarray:
    """P (3, 4) from a parameter vector of ``model``."""
    return compose_projection(*krt_from_params(params, model, reference_K))


def projections_from_params(params: np.ndarray, model: str, reference_K: np.ndarray | None = None) -> np.ndarray:
    """P (B, 3, 4) of B parameter vectors (B, n_params(model)) at once, as
    :func:`projection_from_params` gives them one by one; reference_K (3, 3) or (B, 3, 3). The
    BA evaluates every free camera, and its finite-difference derivatives, each iteration."""
    params = np.asarray(params, np.float64)
    ni = N_INTRINSICS[_check(model)]
    K = Ks_from_intrinsics(params[:, :ni], model, reference_K)
    Rt = np.concatenate([rotations_from_vectors(params[:, ni:ni + 3]), params[:, ni + 3:ni + 6, None]], axis=2)
    return K @ Rt


def project_to_model(P: np.ndarray, model: str, reference_K: np.ndarray | None = None) -> np.ndarray:
    """The camera of ``model``'s family closest to P (same centre and rotation)."""
    params, ref = params_from_projection(P, model, reference_K)
    return projection_from_params(params, model, ref)


def projection_derivatives(K: np.ndarray, R: np.ndarray, t: np.ndarray, model: str,
                           reference_K: np.ndarray | None = None) -> np.ndarray:
    """dP/dparam, (n_params(model), 3, 4), of P = K [R | t], analytic.

    The parameters are the model's intrinsics, then a rotation *increment* w applied on the left
    (R <- exp([w]x) R, so dR/dw_j = [e_j]x R at w = 0), then t. A refinement that moves R by
    such increments stays away from the rotation vector's singularity at pi."""
    Rt = np.hstack([R, np.reshape(t, (3, 1))])
    dK = _intrinsic_derivatives(model, reference_K)
    ni = len(dK)
    out = np.zeros((ni + 6, 3, 4))
    if ni:
        out[:ni] = np.matmul(np.array(dK), Rt)
    zero = np.zeros(3)
    # [e_j]x R for j = x, y, z, written out (rows of R crossed into place)
    skew_R = np.array([[zero, -R[2], R[1]], [R[2], zero, -R[0]], [-R[1], R[0], zero]])
    out[ni:ni + 3, :, :3] = np.matmul(K, skew_R)
    out[ni + 3:, :, 3] = K.T
    return out


def linear_K(intr: np.ndarray, model: str, reference_K: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """K of the intrinsics ``intr`` as K_base + sum_i intr[i] dK[i]: (K_base (3, 3), dK (n, 3, 3)),
    K being linear in every model's intrinsics."""
    dK = np.array(_intrinsic_derivatives(model, reference_K)).reshape(-1, 3, 3)
    intr = np.asarray(intr, np.float64)
    return K_from_intrinsics(intr, model, reference_K) - np.tensordot(intr, dK, axes=1), dK


def _intrinsic_derivatives(model: str, reference_K: np.ndarray | None) -> list[np.ndarray]:
    """dK/d(intrinsic parameter), one (3, 3) matrix per intrinsic of ``model`` (K is linear in
    them, so these are constants)."""
    def unit(*entries: tuple[int, int]) -> np.ndarray:
        d = np.zeros((3, 3))
        for r, c in entries:
            d[r, c] = 1.0
        return d

    if _check(model) == CameraModel.FREE:  # fx, fy, skew, cx, cy
        return [unit((0, 0)), unit((1, 1)), unit((0, 1)), unit((0, 2)), unit((1, 2))]
    if model == CameraModel.ZERO_SKEW:  # f, cx, cy
        return [unit((0, 0), (1, 1)), unit((0, 2)), unit((1, 2))]
    if model == CameraModel.FIXED:
        return []
    ref = _require_reference(reference_K)  # focal: K = reference_K with its 2x2 block scaled by f / f_ref
    d = np.zeros((3, 3))
    d[:2, :2] = np.triu(ref[:2, :2]) / ref[0, 0]
    return [d]
