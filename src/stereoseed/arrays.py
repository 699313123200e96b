"""Small array helpers the pipeline's hot paths share."""
from __future__ import annotations

import numpy as np

__all__ = ["unique"]


def unique(values: np.ndarray) -> np.ndarray:
    """The sorted distinct values of an integer array (flattened), as ``np.unique(values)``.

    By a sort and a comparison of neighbours: NumPy 2.4's ``np.unique`` without ``return_*``
    takes a hashing path that is 2-13x slower than sorting (measured on 1e3-1e6 int64 values;
    0.72 s against 0.05 s at a million), and it runs on every observation of the model after
    each insertion.
    """
    s = np.sort(np.asarray(values).ravel())
    return s[np.r_[True, s[1:] != s[:-1]]] if len(s) else s
