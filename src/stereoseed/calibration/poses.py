"""Rigid motions as 6-vectors (rotation vector, translation: X -> R X + t), the form the
calibration's parameters take, and the few operations on them it needs."""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["to_rt", "from_rt", "compose", "inverse", "mean_pose", "angle_deg", "IDENTITY"]

IDENTITY = np.zeros(6)


def to_rt(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(np.asarray(pose[:3], np.float64))[0], np.asarray(pose[3:], np.float64).copy()


def from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel(), np.asarray(t, np.float64).ravel()])


def compose(*poses: np.ndarray) -> np.ndarray:
    """compose(a, b, c) = a o b o c: c applied first."""
    R, t = np.eye(3), np.zeros(3)
    for pose in reversed(poses):
        Rp, tp = to_rt(pose)
        R, t = Rp @ R, Rp @ t + tp
    return from_rt(R, t)


def inverse(pose: np.ndarray) -> np.ndarray:
    R, t = to_rt(pose)
    return from_rt(R.T, -R.T @ t)


def mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """A robust mean of nearby poses: the rotation nearest the mean of the rotation matrices
    (the chordal L2 mean), the per-axis median of the translations."""
    Rs = [to_rt(p)[0] for p in poses]
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return from_rt(R, np.median([p[3:] for p in poses], axis=0))


def angle_deg(pose: np.ndarray) -> float:
    """The rotation angle of a pose, degrees."""
    return float(np.degrees(np.linalg.norm(pose[:3])))
