"""Cameras and their conventions: the :class:`Camera` value type, the :class:`CameraModel`
parameterisations, the lens, and projective geometry on raw arrays (the bottom layer: it imports
nothing else of stereoseed)."""
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.models import CameraModel

__all__ = ["Camera", "CameraModel"]
