"""The Huber loss on 2D reprojection errors, as the bundle adjustment and the single-camera
refinement (its compiled loop, :mod:`stereoseed.estimators._calibration_kernels`) use it: quadratic up to
``delta`` px, linear beyond (Huber 1964), on each point's error *norm*, so that the cost does
not depend on the image axes."""
from __future__ import annotations

import numpy as np

__all__ = ["huber_cost", "huber_cost_of_norms"]


def huber_cost(r: np.ndarray, delta: float) -> float:
    """Sum of the Huber costs of the 2D residual norms. r: (O, 2); delta=inf gives the sum of
    squares."""
    return huber_cost_of_norms(np.linalg.norm(r, axis=1), delta)


def huber_cost_of_norms(norm: np.ndarray, delta: float) -> float:
    """:func:`huber_cost` of residuals whose norms (O,) are already known."""
    if not np.isfinite(delta):
        return float(np.sum(norm * norm))
    return float(np.sum(np.where(norm <= delta, norm ** 2, 2 * delta * norm - delta ** 2)))
