"""A view: one input image and what the run knows of it (its camera, interest points, the links
of its interest points to 3D points, and the history of its camera's life)."""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable

import numpy as np

from stereoseed.features.harris import Features
from stereoseed.features.image import to_gray
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.projection import camera_center, intrinsics_turned_180
from stereoseed.scene.camera_life import Event, Flag, Life, life_of

__all__ = ["View", "intrinsics_in_frame"]


def intrinsics_in_frame(K: np.ndarray, source_turned: bool, turned: bool, image_size: tuple[int, int]) -> np.ndarray:
    """Intrinsics K (3, 3) of an image (turned by 180 degrees or not) expressed for an image of
    ``image_size`` (width, height) that is ``turned`` or not."""
    return K if source_turned == turned else intrinsics_turned_180(K, image_size)


class View:
    """One input image and what the run knows of it.

    name: file name; image: uint8 BGR (H, W, 3) as the run works on it (turned by 180 degrees
    when ``rotated_180``); features: its interest points; P: (3, 4) camera in that image's
    frame, None while unregistered; point_of_feature: (N,) int64, the 3D point each interest
    point stands for (-1: none); camera_model: the camera model its intrinsics follow when it
    is not the run's (an 11-DOF camera refused, the focal-only model taken instead); zoomed: its
    resection took a new focal length rather than the previous image's.

    ``history``: the events of the camera's life (:mod:`stereoseed.scene.camera_life`); its
    status, flags and what placed it are read from it (``status``, ``placement_flag``,
    ``flag``, ``found_by``), and only :class:`~stereoseed.scene.reconstruction.Reconstruction`
    appends to it.

    P is a read-only copy of what was set; K, R and focal are decomposed from it once, on first
    use after it was set (the camera's RQ decomposition is not repeated).
    """

    def __init__(self, name: str, features: Features | None = None, P: np.ndarray | None = None,
                 point_of_feature: np.ndarray | None = None,
                 image: np.ndarray | None = None, rotated_180: bool = False, camera_model: str | None = None,
                 zoomed: bool = False, load: Callable[[], np.ndarray] | None = None):
        self.name = name
        self.features = features
        self.point_of_feature = np.zeros(0, np.int64) if point_of_feature is None else point_of_feature
        self._load = load
        self._size: tuple[int, int] | None = None
        self.image = image
        self._gray_released = False
        self.rotated_180 = rotated_180
        self.camera_model = camera_model
        self.zoomed = zoomed
        self._camera: Camera | None = None
        self.P = P
        self.history: tuple[Event, ...] = ()
        self.life = Life()  # what the history leaves: kept as the history grows
        # its 1-sigma uncertainty from the final BA (stereoseed.sfm.trust), once judged
        self.uncertainty: Any = None

    # ------------------------------------------------------------ its life (read it)
    @property
    def status(self) -> str:
        """"calibrated", "registered", "pending" or "failed: <reason>"."""
        return self.life.text

    @property
    def found_by(self) -> str | None:
        """What placed its camera (registration.base.FoundBy's value), None while unplaced."""
        return self.life.found_by

    @property
    def placement_flag(self) -> Flag | None:
        """The flag raised while the camera was placed (an ambiguous choice, a zoom it could not
        measure), while it stands."""
        return self.life.placement_flag

    @property
    def flag(self) -> Flag | None:
        """Why the run cannot vouch for the camera now (the judgement's, once judged), or None."""
        return self.life.flag

    @property
    def flag_reason(self) -> str | None:
        """:attr:`flag` as the text the outputs write."""
        return None if self.life.flag is None else self.life.flag.reason

    def _record(self, event: Event) -> None:
        self.history = self.history + (event,)
        self.life = self.life.after(event)

    @property
    def features(self) -> Features | None:
        """The interest points (their grey image None after :meth:`release_pixels`, until
        :meth:`restore_gray`)."""
        return self._features

    @features.setter
    def features(self, features: Features | None) -> None:
        self._features = features
        self._gray_released = False

    def restore_gray(self) -> Features | None:
        """The interest points with their grey image, computed again from the image if it was
        released (what matching or tracking against an old view needs)."""
        f = self._features
        if f is not None and f.gray is None and self._gray_released:
            self._features = replace(f, gray=to_gray(self.image))
            self._gray_released = False
        return self._features

    def replace_features(self, **changes: Any) -> None:
        """The same interest points with some arrays exchanged (a memory-mapped ``desc``, ``gray``
        None when the grey image is let go: :func:`restore_gray` computes it again). The pixels'
        residency is :mod:`stereoseed.scene.view_store`'s business; the view only records it."""
        f = self._features
        if f is None or not changes:
            return
        self._features = replace(f, **changes)
        self._gray_released = self._gray_released or ("gray" in changes and changes["gray"] is None)

    @property
    def can_read_image_again(self) -> bool:
        """Whether the view's image can be had again once let go (read from its file, or held)."""
        return self._load is not None or self._image is not None

    def keep_image(self, image: np.ndarray, rotated_180: bool) -> None:
        """The image the run works on: held only when the view cannot read it again (turned, or
        given in memory)."""
        self.image = image if (rotated_180 or self._load is None) else None
        self.rotated_180 = rotated_180

    @property
    def image(self) -> np.ndarray | None:
        """The image as the run works on it: the one set, else the input image read on demand
        through ``load`` (a long sequence does not hold every image)."""
        if self._image is None and self._load is not None:
            return self._load()
        return self._image

    @image.setter
    def image(self, image: np.ndarray | None) -> None:
        self._image = image
        if image is not None:  # letting go of an image (it is read again) keeps its size known
            self._size = (image.shape[1], image.shape[0])

    @property
    def camera(self) -> Camera | None:
        """The view's camera in the frame of the image the run works on; None while unregistered."""
        return self._camera

    @camera.setter
    def camera(self, camera: Camera | None) -> None:
        self._camera = camera

    @property
    def P(self) -> np.ndarray | None:
        return None if self._camera is None else self._camera.P

    @P.setter
    def P(self, P: np.ndarray | None) -> None:
        """A new P keeps the camera model the view's camera had (a refinement moves the camera
        within its model)."""
        if P is None:
            self._camera = None
        else:
            model = self._camera.model if self._camera is not None else CameraModel(self.camera_model or "free")
            self._camera = Camera(P, model)

    @property
    def K(self) -> np.ndarray:
        return self._camera.K

    @property
    def R(self) -> np.ndarray:
        return self._camera.R

    @property
    def center(self) -> np.ndarray:
        return camera_center(self._camera.P)

    @property
    def focal(self) -> float:
        """Focal length (px, along x)."""
        return self._camera.focal

    @property
    def reliable(self) -> bool:
        """Whether the run vouches for the camera (no flag)."""
        return self.life.flag is None

    @property
    def registered(self) -> bool:
        return self._camera is not None

    @property
    def image_size(self) -> tuple[int, int] | None:
        """(width, height) of the image; None for a view without one (a camera alone)."""
        if self._size is None:
            image = self.image
            self._size = None if image is None else (image.shape[1], image.shape[0])
        return self._size

    @property
    def P_input(self) -> np.ndarray | None:
        """P (3, 4) in the pixel frame of the input image (P works in the frame the run used)."""
        if self._camera is None or not self.rotated_180:
            return self.P
        return self._camera.turned_180(self.image_size).P

    def in_frame_of(self, K: np.ndarray, source: "View") -> np.ndarray:
        """Intrinsics K (3, 3) of ``source``'s image expressed for this view's image: turning an
        image by 180 degrees maps pixel (x, y) to (W - 1 - x, H - 1 - y), which moves the
        principal point (focal lengths and skew stay, the roll goes into R)."""
        return intrinsics_in_frame(K, source.rotated_180, self.rotated_180, self.image_size)

    def append_features(self, features: Features) -> np.ndarray:
        """Add interest points found by tracking, not detection; returns their indices (K,)."""
        f = self.features
        start = len(f)
        self.features = Features(np.vstack([f.points, features.points]), np.vstack([f.desc, features.desc]),
                                 np.concatenate([f.valid, features.valid]),
                                 np.concatenate([f.response, features.response]), f.image_shape, f.gray)
        self.point_of_feature = np.concatenate([self.point_of_feature, np.full(len(features), -1, np.int64)])
        return np.arange(start, start + len(features))

    def _state(self) -> tuple:
        """(P, features, point_of_feature, image, rotated_180, camera_model, zoomed, grey image
        released, history)."""
        return (self.P, self._features, self.point_of_feature.copy(), self._image, self.rotated_180,
                self.camera_model, self.zoomed, self._gray_released, self.history)

    def _restore(self, state: tuple) -> None:
        P, self.features, self.point_of_feature, self.image, self.rotated_180, self.camera_model, \
            self.zoomed, self._gray_released, self.history = state
        self.life = life_of(self.history)
        self._camera = None  # the restored P follows the restored camera_model, not the current camera's model
        self.P = P
