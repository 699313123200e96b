"""The Huber loss on 2D reprojection errors, shared by the single-camera refinement and the
bundle adjustment: quadratic up to ``delta`` px, linear beyond (Huber 1964), on each point's
error *norm*, so that the cost does not depend on the image axes."""
from __future__ import annotations

import numpy as np

__all__ = ["huber_weights", "huber_cost"]


def huber_weights(r: np.ndarray, delta: float) -> np.ndarray:
    """IRLS weights of the Huber loss on the 2D residual norm. r: (O, 2) -> (O,); delta=inf
    gives least squares (all ones)."""
    norm = np.linalg.norm(r, axis=1)
    return np.where(norm <= delta, 1.0, delta / np.maximum(norm, 1e-300))


def huber_cost(r: np.ndarray, delta: float) -> float:
    """Sum of the Huber costs of the 2D residual norms. r: (O, 2); delta=inf gives the sum of
    squares."""
    norm = np.linalg.norm(r, axis=1)
    if not np.isfinite(delta):
        return float(np.sum(norm * norm))
    return float(np.sum(np.where(norm <= delta, norm ** 2, 2 * delta * norm - delta ** 2)))
