"""Cameras and their conventions: the :class:`Camera` value type, the :class:`CameraModel`
parameterisations, the lens, and projective geometry on raw arrays (the bottom layer: it imports
nothing else of stereoseed)."""
from typing import Any

__all__ = ["Camera", "CameraModel"]


def __getattr__(name: str) -> Any:
    # imported when asked for: the configuration imports geometry.camera_model before the command
    # has set NumPy's BLAS threads, and Camera needs NumPy
    if name == "Camera":
        from stereoseed.geometry.camera import Camera
        return Camera
    if name == "CameraModel":
        from stereoseed.geometry.camera_model import CameraModel
        return CameraModel
    raise AttributeError(f"module 'stereoseed.geometry' has no attribute {name!r}")
