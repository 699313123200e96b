"""The camera models by name: which intrinsics of a camera are free. No NumPy here: the
configuration imports it, and the command sets its BLAS threads before NumPy loads
(:mod:`stereoseed.geometry.models` holds the parameterisations' arithmetic)."""
from __future__ import annotations

from enum import StrEnum

__all__ = ["CameraModel", "MODELS", "N_INTRINSICS"]


class CameraModel(StrEnum):
    """Which intrinsics of a camera are free; the model owns its parameterisation (intrinsics,
    then a rotation vector (3), then t (3)). Its value is the name used in configs and reports."""

    FREE = "free"
    ZERO_SKEW = "zero-skew"
    FOCAL = "focal"
    FIXED = "fixed"

    @property
    def n_intrinsics(self) -> int:
        return N_INTRINSICS[self]

    @property
    def n_params(self) -> int:
        return N_INTRINSICS[self] + 6

    @property
    def needs_reference(self) -> bool:
        """Whether its intrinsics are relative to a reference camera's K (the calibrated one)."""
        return self in (CameraModel.FOCAL, CameraModel.FIXED)


MODELS = tuple(m.value for m in CameraModel)
N_INTRINSICS = {CameraModel.FREE: 5, CameraModel.ZERO_SKEW: 3, CameraModel.FOCAL: 1, CameraModel.FIXED: 0}
