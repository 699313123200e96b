"""The camera value type: a pinhole camera P = K [R | t] with its model and, where there is one,
its lens.

A :class:`Camera` is immutable. Built from P (what the estimators return) it keeps that P bit for
bit and decomposes it into K, R, t once, on first use; built from K, R, t (or from a model's
parameters) it composes P once. Conventions: :mod:`stereoseed.geometry.projection`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from stereoseed.geometry.models import CameraModel, krt_from_params, params_from_projection
from stereoseed.arrays import read_only_float64
from stereoseed.geometry.projection import (camera_center, compose_projection, decompose_projection, depths,
                                            intrinsics_turned_180, project)

__all__ = ["Camera"]


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera.

    P: (3, 4) float64, read-only; model: the :class:`CameraModel` its intrinsics follow;
    lens: OpenCV's (k1, k2, p1, p2, k3) of the image it looks through, or None (the pixels are
    undistorted). K (3, 3), R (3, 3) and t (3,) are P's decomposition (``cam_from_world``).
    """

    P: np.ndarray
    model: CameraModel = CameraModel.FREE
    lens: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "P", read_only_float64(self.P))
        object.__setattr__(self, "model", CameraModel(self.model))
        if self.lens is not None:
            object.__setattr__(self, "lens", read_only_float64(self.lens))

    @classmethod
    def from_krt(cls, K: np.ndarray, R: np.ndarray, t: np.ndarray, model: CameraModel = CameraModel.FREE,
                 lens: np.ndarray | None = None) -> "Camera":
        """The camera K [R | t]; its K, R, t are the ones given (no decomposition)."""
        cam = cls(compose_projection(K, R, t), model, lens)
        cam.__dict__["_krt"] = tuple(read_only_float64(a) for a in (K, R, np.ravel(t)))
        return cam

    @classmethod
    def from_params(cls, params: np.ndarray, model: CameraModel, reference_K: np.ndarray | None = None,
                    lens: np.ndarray | None = None) -> "Camera":
        """The camera of a parameter vector of ``model`` (:meth:`params`)."""
        return cls.from_krt(*krt_from_params(params, model, reference_K), model=model, lens=lens)

    @cached_property
    def _krt(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(read_only_float64(a) for a in decompose_projection(self.P))

    @property
    def krt(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K (3, 3), R (3, 3), t (3,)), read-only."""
        return self._krt

    @property
    def K(self) -> np.ndarray:
        return self._krt[0]

    @property
    def R(self) -> np.ndarray:
        return self._krt[1]

    @property
    def t(self) -> np.ndarray:
        return self._krt[2]

    @property
    def focal(self) -> float:
        """Focal length (px, along x)."""
        return float(self.K[0, 0])

    @cached_property
    def centre(self) -> np.ndarray:
        """The camera centre C (3,), with P @ (C, 1) = 0."""
        return camera_center(self.P)

    def project(self, X: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points X (N, 3) (undistorted pixels: the lens is not applied)."""
        return project(self.P, X)

    def depths(self, X: np.ndarray) -> np.ndarray:
        """Depth (N,) of world points X (N, 3) along the optical axis."""
        return depths(self.P, X)

    def params(self, reference_K: np.ndarray | None = None) -> np.ndarray:
        """The parameter vector of this camera under its model (intrinsics, rotation vector, t);
        the "focal" and "fixed" models are relative to ``reference_K``."""
        return params_from_projection(self.P, self.model, reference_K)[0]

    def turned_180(self, image_size: tuple[int, int]) -> "Camera":
        """The same camera for its image turned by 180 degrees (``image_size`` = (width, height)
        of the image it sees): pixel (x, y) becomes (W - 1 - x, H - 1 - y)."""
        w, h = image_size
        flip = np.array([[-1.0, 0.0, w - 1.0], [0.0, -1.0, h - 1.0], [0.0, 0.0, 1.0]])
        return Camera(flip @ self.P, self.model, self.lens)

    def K_turned_180(self, image_size: tuple[int, int]) -> np.ndarray:
        """K (3, 3) of this camera for its image turned by 180 degrees."""
        return intrinsics_turned_180(self.K, image_size)
