"""The Huber loss on 2D reprojection errors, as the bundle adjustment and the single-camera
refinement (its compiled loop, :mod:`stereoseed.estimators._calibration_kernels`) use it: quadratic up to
``delta`` px, linear beyond (Huber 1964), on each point's error *norm*, so that the cost does
not depend on the image axes."""
from __future__ import annotations

import numpy as np

__all__ = ["huber_cost", "huber_cost_of_norms", "huber_weights"]


def huber_cost(r: np.ndarray, delta: float) -> float:
    """Sum of the Huber costs of the 2D residual norms. r: (O, 2); delta=inf gives the sum of
    squares."""
    return huber_cost_of_norms(np.linalg.norm(r, axis=1), delta)


def huber_cost_of_norms(norm: np.ndarray, delta: float) -> float:
    """:func:`huber_cost` of residuals whose norms (O,) are already known."""
    if not np.isfinite(delta):
        return float(np.sum(norm * norm))
    return float(np.sum(np.where(norm <= delta, norm ** 2, 2 * delta * norm - delta ** 2)))


def huber_weights(norm: np.ndarray, delta: float) -> np.ndarray:
    """The iteratively reweighted least-squares weights (O,) of the Huber cost at residual norms
    (O,): 1 up to ``delta``, delta / norm beyond; all 1 for delta=inf (least squares)."""
    if not np.isfinite(delta):
        return np.ones(len(norm))
    return np.where(norm <= delta, 1.0, delta / np.maximum(norm, 1e-300))
