"""Robust estimation of a new camera P_k from 3D-2D pairs (paper §4.2, eq. 10-11).

RANSAC over 6-point DLT samples (drawn with a preference for high-NCC points spread over the
image, as the paper chooses its N points), refit on the inliers, then LM on the reprojection
error under the chosen camera model.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from stereoseed.estimators.calibration import (check_correspondences, dlt_projection, normalization_2d, normalization_3d,
                          refine_projection)
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.projection import depths, is_finite_camera, normalize_projection, project
from stereoseed.estimators.config import ResectionConfig
from stereoseed.errors import StereoseedError
from stereoseed.estimators._resection_kernels import choose_samples, score_hypotheses
from stereoseed.geometry.models import CameraModel

__all__ = ["ResectionResult", "implausible_intrinsics", "resect"]


@dataclass
class ResectionResult:
    """camera: the estimate, its model the one asked for or "fixed" when the previous image's
    intrinsics were kept; inliers (N,) bool; rms_px over inliers; n_hypotheses tried; info:
    n_pairs, n_inliers, model (the camera's, as the report names it)."""

    camera: Camera
    inliers: np.ndarray
    rms_px: float
    n_hypotheses: int
    info: dict = field(default_factory=dict)

    @property
    def P(self) -> np.ndarray:
        return self.camera.P


def _draw_samples(rng: np.random.Generator, n_samples: int, p: np.ndarray, cells: np.ndarray,
                  distinct_cells: bool) -> np.ndarray:
    """6-point samples (n_samples, 6), points drawn with probabilities p (N,), from 6 distinct
    image cells (cells (N,)) when ``distinct_cells`` (the points cover enough cells: spread over
    the image makes the DLT well conditioned): the first fitting of 12 weighted draws,
    completed by uniform draws."""
    draws = rng.choice(len(p), size=(n_samples, 12), p=p)
    return choose_samples(rng, draws, cells, distinct_cells)


def _pnp_start(X: np.ndarray, x: np.ndarray, K: np.ndarray, config: ResectionConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """P3P RANSAC (OpenCV) with intrinsics K (3, 3): a starting camera and its inliers, or None.
    The threshold is widened because the true focal length may differ from K's."""
    if len(X) < 6:
        return None
    # OpenCV's RANSAC registrator seeds its own generator: deterministic without cv2.setRNGSeed
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, x, K, None, iterationsCount=int(config.ransac_max_iters),
                                             reprojectionError=3.0 * config.ransac_threshold_px,
                                             confidence=config.ransac_confidence, flags=cv2.SOLVEPNP_AP3P)
    if not ok or inl is None or len(inl) < max(config.min_points, config.min_inliers):
        return None
    inliers = np.zeros(len(X), bool)
    inliers[inl.ravel()] = True
    return K @ np.hstack([cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)]), inliers


def _unless_unchanged_zoom_fits(P: np.ndarray, inliers: np.ndarray, rms: float, X: np.ndarray, x: np.ndarray,
                                fallback_K: np.ndarray, config: ResectionConfig, polish
                                ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """Model selection between a focal-only camera (P, inliers, rms) and the previous image's
    intrinsics (``fallback_K``: the zoom did not move). With a narrow field of view and few
    points the focal length trades against the depth and one image cannot tell them apart
    (measured on templeSparseRing: a 34-point resection 9 % off in focal length, 40 mm off in
    position); the extra parameter must then pay for itself. BIC on the focal camera's inliers
    (Schwarz 1978; Torr's GRIC makes the same choice here): n ln(RSS / n) + k ln(n), k = 7 or 6;
    the new focal length must win by ``config.zoom_evidence_bic``.
    """
    cam = Camera(P)  # the focal camera's pose is a close start
    R, t = cam.R, cam.t
    P_fixed, inl_fixed, rms_fixed = polish(fallback_K @ np.hstack([R, t.reshape(3, 1)]), inliers,
                                           model=CameraModel.FIXED, reference_K=fallback_K)
    if rms_fixed > config.max_rms_px or inl_fixed.sum() < config.min_inliers:
        return P, inliers, rms, CameraModel.FOCAL
    n = 2 * int(inliers.sum())

    def bic(Pc: np.ndarray, k: int) -> float:
        rss = float(np.sum((project(Pc, X[inliers]) - x[inliers]) ** 2))
        return n * np.log(max(rss, 1e-12) / n) + k * np.log(n)

    if bic(P_fixed, 6) <= bic(P, 7) + config.zoom_evidence_bic:
        return P_fixed, inl_fixed, rms_fixed, CameraModel.FIXED
    return P, inliers, rms, CameraModel.FOCAL


def resect(points3d: np.ndarray, points2d: np.ndarray, config: ResectionConfig = ResectionConfig(),
           scores: np.ndarray | None = None, image_size: tuple[int, int] | None = None,
           model: str = "free", reference_K: np.ndarray | None = None, what: str = "resection",
           fallback_K: np.ndarray | None = None) -> ResectionResult:
    """Estimate P from 3D-2D pairs robustly.

    points3d: (N, 3); points2d: (N, 2); scores: (N,) NCC score of each pair's match (higher is
    better) or None; image_size: (width, height) for the spread criterion. Raises
    :class:`StereoseedError` when there are too few pairs, they are coplanar, or too few inliers.
    """
    X, x = check_correspondences(points3d, points2d, config.coplanarity_tol, what=what)
    n = len(X)
    rng = np.random.default_rng(config.seed)
    weights = np.ones(n) if scores is None else np.clip(np.asarray(scores, float), 1e-3, None) ** 4
    if image_size is None:
        image_size = (x[:, 0].max() + 1, x[:, 1].max() + 1)
    grid = 4
    cx = np.clip((x[:, 0] / image_size[0] * grid).astype(int), 0, grid - 1)
    cy = np.clip((x[:, 1] / image_size[1] * grid).astype(int), 0, grid - 1)
    cells = cy * grid + cx

    T = normalization_2d(x)
    U = normalization_3d(X)
    Xn = np.hstack([X, np.ones((n, 1))]) @ U.T
    xn = np.hstack([x, np.ones((n, 1))]) @ T.T
    Xh = np.hstack([X, np.ones((n, 1))])
    T_inv = np.linalg.inv(T)
    draw_p, distinct_cells = weights / weights.sum(), len(np.unique(cells)) >= 6
    thr2 = config.ransac_threshold_px ** 2

    best_inliers = np.zeros(n, dtype=bool)
    best_count = 0
    tried = 0
    max_iters = config.ransac_max_iters
    batch = 128
    while tried < max_iters:
        samples = _draw_samples(rng, batch, draw_p, cells, distinct_cells)
        # the DLT of each sample and its inliers (within the threshold, in front of the camera)
        _, inl, counts = score_hypotheses(Xn, xn, samples, T_inv, U, Xh, np.ascontiguousarray(x), thr2)
        s = int(np.argmax(counts))
        tried += batch
        if counts[s] > best_count:
            best_count = int(counts[s])
            best_inliers = inl[s]
            ratio = best_count / n
            # standard adaptive stopping (Fischler & Bolles; HZ §4.7.1)
            denom = np.log(max(1e-12, 1.0 - ratio ** 6))
            needed = np.log(1.0 - config.ransac_confidence) / denom if denom < 0 else 0
            max_iters = min(config.ransac_max_iters, max(batch, int(np.ceil(needed))))
    if best_count < max(config.min_points, config.min_inliers):
        raise StereoseedError(
            f"{what}: only {best_count} of {n} 3D-2D pairs agree on a camera "
            f"(need {max(config.min_points, config.min_inliers)}); too few correct matches")

    def polish(P: np.ndarray, inliers: np.ndarray, model: str = model, reference_K: np.ndarray | None = reference_K
               ) -> tuple[np.ndarray, np.ndarray, float]:
        for _ in range(2):  # refit, re-select inliers, refine: converges in one or two rounds
            P = refine_projection(P, X[inliers], x[inliers], model=model, reference_K=reference_K,
                                  loss="huber", f_scale=config.ransac_threshold_px / 2)
            if not is_finite_camera(P):  # a rank-deficient start collapses: no camera
                return P, inliers, np.inf
            err2 = np.sum((project(P, X) - x) ** 2, axis=1)
            new_inliers = (err2 < thr2) & (depths(P, X) > 0)
            if new_inliers.sum() < config.min_inliers or np.array_equal(new_inliers, inliers):
                break
            inliers = new_inliers
        if is_finite_camera(P):  # a camera that degenerated (an affine camera fits a plane) stays as it is
            P = normalize_projection(refine_projection(P, X[inliers], x[inliers], model=model, reference_K=reference_K))
        err2 = np.sum((project(P, X[inliers]) - x[inliers]) ** 2, axis=1)
        return P, inliers, float(np.sqrt(np.mean(err2)))

    def polished(starts: list, **model_args) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """The cameras polished from the finite starts (P, inliers) (None: no start), those
        that did not collapse."""
        cameras = (polish(*s, **model_args) for s in starts if s is not None and is_finite_camera(s[0]))
        return [c for c in cameras if np.isfinite(c[2])]

    starts = [(dlt_projection(X[best_inliers], x[best_inliers]), best_inliers)]
    if model != CameraModel.FREE and reference_K is not None:
        # The DLT is ill-conditioned when the points are nearly planar (one face of an object
        # in view); a constrained camera can start from P3P with the reference intrinsics.
        starts.append(_pnp_start(X, x, reference_K, config))
    candidates = polished(starts)

    def plausible(P: np.ndarray) -> bool:
        # a near-planar point set lets the LM run the focal length off to infinity (an affine
        # camera fits a plane): such a camera is no candidate
        if reference_K is None:
            return True
        f, f_ref = Camera(P).focal, reference_K[0, 0]
        return bool(np.isfinite(f) and f_ref / 3 <= f <= 3 * f_ref)

    if fallback_K is not None and not any(plausible(c[0]) for c in candidates):
        start = _pnp_start(X, x, fallback_K, config)
        if start is not None:
            model, reference_K = CameraModel.FIXED, np.asarray(fallback_K, np.float64)
            candidates = polished([start], model=model, reference_K=reference_K)
    if not candidates:
        raise StereoseedError(f"{what}: the {best_count} agreeing 3D-2D pairs are degenerate (no finite camera)")
    P, inliers, rms = max(candidates, key=lambda c: (plausible(c[0]), c[2] <= config.max_rms_px, c[1].sum(), -c[2]))
    if model == CameraModel.FOCAL and fallback_K is not None:
        P, inliers, rms, model = _unless_unchanged_zoom_fits(P, inliers, rms, X, x, np.asarray(fallback_K, np.float64),
                                                             config, polish)
    if rms > config.max_rms_px:
        raise StereoseedError(f"{what}: the best camera reprojects its inliers with {rms:.2f} px RMS "
                              f"(limit {config.max_rms_px} px); the 3D-2D pairs are inconsistent")
    return ResectionResult(camera=Camera(P, model), inliers=inliers, rms_px=rms, n_hypotheses=tried,
                           info={"n_pairs": n, "n_inliers": int(inliers.sum()), "model": model})


def implausible_intrinsics(P: np.ndarray, reference_K: np.ndarray, image_size: tuple[int, int],
                           config: ResectionConfig = ResectionConfig()) -> str | None:
    """Why the intrinsics of camera P (3, 4) cannot be a physical camera's, or None when they
    can: compared with ``reference_K`` (3, 3), the calibrated camera of the same sequence, its
    principal point moved by more than ``max_principal_point_shift`` of the image diagonal
    (``image_size`` = (width, height)), or its pixel aspect or skew left their bounds. A free
    (11-DOF) resection from a weak point set trades the focal length against the distance and
    the principal point against the orientation, and lands on such cameras."""
    K = Camera(P).K
    K = K / K[2, 2]
    ref = reference_K / reference_K[2, 2]
    shift = float(np.hypot(K[0, 2] - ref[0, 2], K[1, 2] - ref[1, 2]))
    diagonal = float(np.hypot(*image_size))
    if not shift <= config.max_principal_point_shift * diagonal:
        return f"principal point {shift:.0f} px from the calibrated camera's"
    aspect = (K[1, 1] / K[0, 0]) / (ref[1, 1] / ref[0, 0])
    if not abs(aspect - 1.0) <= config.max_aspect_change:
        return f"pixel aspect ratio {100 * (aspect - 1):+.1f} % off the calibrated camera's"
    skew = K[0, 1] / K[0, 0] - ref[0, 1] / ref[0, 0]
    if not abs(skew) <= config.max_skew:
        return f"skew {skew:+.3f} (relative to the focal length)"
    return None
