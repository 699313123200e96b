"""The reconstruction's data model: views (an image, its camera and interest points), 3D points
with colour, and the observations linking an interest point of a view to a 3D point.

Modelled on COLMAP's ``scene/`` (Camera, Image, Point3D and the observation manager): a point's
track is the list of its observations, and :class:`Reconstruction` alone changes them, keeping
its invariants:

* an interest point stands for at most one 3D point (``View.point_of_feature``), and a linked
  observation is the one it stands for;
* the paper mode's *unlinked* observations are explicit: a chained old point observed in I_k
  enters the cost, while the interest point keeps standing for the new two-view point;
* removed points keep their index (``alive`` is False), so indices held elsewhere stay valid.

Points and observations live in flat NumPy arrays that grow by doubling, so the pipeline's
steps stay vectorised and appending does not copy everything each time.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, Iterator

import numpy as np

from stereoseed.estimators.bundle import observation_errors
from stereoseed.geometry.camera import Camera
from stereoseed.geometry.models import CameraModel
from stereoseed.geometry.projection import camera_center, intrinsics_turned_180
from stereoseed.features.harris import Features
from stereoseed.features.image import to_gray

__all__ = ["View", "Reconstruction", "Checkpoint", "eq14", "intrinsics_in_frame"]


def intrinsics_in_frame(K: np.ndarray, source_turned: bool, turned: bool, image_size: tuple[int, int]) -> np.ndarray:
    """Intrinsics K (3, 3) of an image (turned by 180 degrees or not) expressed for an image of
    ``image_size`` (width, height) that is ``turned`` or not."""
    return K if source_turned == turned else intrinsics_turned_180(K, image_size)


def eq14(sum_squared_px: float, n_images: int, n_points: int) -> float:
    """The paper's eq. 14: sum of squared reprojection errors over images x points (px^2, not
    rooted, as the paper prints it)."""
    return float(sum_squared_px / max(1, n_images * n_points))


class View:
    """One input image and what the run knows of it.

    name: file name; image: uint8 BGR (H, W, 3) as the run works on it (turned by 180 degrees
    when ``rotated_180``); features: its interest points; P: (3, 4) camera in that image's
    frame, None while unregistered; status: "calibrated", "registered", "pending" or
    "failed: <reason>"; point_of_feature: (N,) int64, the 3D point each interest point stands
    for (-1: none); camera_model: the camera model its intrinsics follow when it is not the
    run's (an 11-DOF camera refused, the focal-only model taken instead); zoomed: its resection
    took a new focal length rather than the previous image's.

    P is a read-only copy of what was set; K, R and focal are decomposed from it once, on first
    use after it was set (the camera's RQ decomposition is not repeated).
    """

    def __init__(self, name: str, features: Features | None = None, P: np.ndarray | None = None,
                 status: str = "pending", point_of_feature: np.ndarray | None = None,
                 image: np.ndarray | None = None, rotated_180: bool = False, camera_model: str | None = None,
                 zoomed: bool = False, load: Callable[[], np.ndarray] | None = None):
        self.name = name
        self.features = features
        self.status = status
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
        # why its registration could not vouch for the camera (an ambiguous choice), set when it
        # is committed; then what the finishing step says (stereoseed.sfm.trust): whether the run
        # can vouch for it, why not, and its 1-sigma uncertainty from the final BA
        self.registration_flag: str | None = None
        self.flag_reason: str | None = None
        # what placed its camera (registration.base.FoundBy), set when it is committed (a
        # checkpoint gives it back from the saved reports)
        self.found_by: str | None = None
        self.uncertainty: Any = None

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
        residency is :mod:`stereoseed.sfm.view_store`'s business; the view only records it."""
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
        """Whether the run vouches for the camera (no ``flag_reason``)."""
        return self.flag_reason is None

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
        """(P, features, point_of_feature, image, status, rotated_180, camera_model, zoomed,
        grey image released, registration flag, what placed the camera)."""
        return (self.P, self._features, self.point_of_feature.copy(), self._image, self.status, self.rotated_180,
                self.camera_model, self.zoomed, self._gray_released, self.registration_flag, self.found_by)

    def _restore(self, state: tuple) -> None:
        P, self.features, self.point_of_feature, self.image, self.status, self.rotated_180, self.camera_model, \
            self.zoomed, self._gray_released, self.registration_flag, self.found_by = state
        self.flag_reason = self.registration_flag  # the final judgement (trust.assess) comes after the last insertion
        self._camera = None  # the restored P follows the restored camera_model, not the current camera's model
        self.P = P


def _rows_by_value(values: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(value, the indices (K,) of its rows) for each distinct value of ``values`` (O,) int: one
    sort, not a scan of every row per value (a long sequence has hundreds of views)."""
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    bounds = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    for start, end in zip(np.r_[0, bounds], np.r_[bounds, len(values)]):
        if end > start:
            yield int(ordered[start]), order[start:end]


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class _Growing:
    """A 1-D or 2-D array that grows by doubling: ``data`` is the used part, a view of the
    buffer, valid until the next extend / keep / set (hold indices, not these views)."""

    def __init__(self, dtype: Any, width: int | None = None):
        self._buf = np.zeros((16,) if width is None else (16, width), dtype)
        self.n = 0

    @property
    def data(self) -> np.ndarray:
        return self._buf[:self.n]

    def extend(self, values: np.ndarray) -> None:
        k = len(values)
        if self.n + k > len(self._buf):
            grown = np.zeros((max(2 * len(self._buf), self.n + k),) + self._buf.shape[1:], self._buf.dtype)
            grown[:self.n] = self._buf[:self.n]
            self._buf = grown
        self._buf[self.n:self.n + k] = values
        self.n += k

    def keep(self, mask: np.ndarray) -> None:
        kept = self.data[mask]
        self._buf[:len(kept)] = kept
        self.n = len(kept)

    def set(self, values: np.ndarray) -> None:
        self.n = 0
        self.extend(values)


@dataclass(frozen=True)
class Checkpoint:
    """What :meth:`Reconstruction.restore` needs to undo what an insertion does to the
    reconstruction: points, colours, observations, and each view's camera, interest points (by
    reference: Features are replaced, never changed in place), links, image and flags. The
    correspondence source's caches are not part of it (keyed by the Features objects, they
    cannot serve a rolled-back insertion's features again)."""

    points: np.ndarray
    colors: np.ndarray
    alive: np.ndarray
    observations: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    views: tuple[tuple, ...]


class Reconstruction:
    """Views, points (M, 3) with colours (M, 3) uint8 RGB, and observations.

    Observations are parallel int64 arrays (obs_view, obs_feature, obs_point) and a bool array
    obs_linked: interest point ``obs_feature`` of view ``obs_view`` is an image of 3D point
    ``obs_point``. Read them through the properties (views of growing buffers: valid until the
    next change); change them through the methods.

    """

    def __init__(self, views: list[View], rig=None):
        self.views = views
        # a stereo rig walked with both cameras (:class:`stereoseed.estimators.rig_resection.Rig`):
        # views 2s and 2s + 1 are station s's left and right images (stereoseed.sfm.rig); None: one
        # moving camera after the pair
        self.rig = rig
        self._points = _Growing(np.float64, 3)
        self._colors = _Growing(np.uint8, 3)
        self._alive = _Growing(bool)
        self._obs_view = _Growing(np.int64)
        self._obs_feature = _Growing(np.int64)
        self._obs_point = _Growing(np.int64)
        self._obs_linked = _Growing(bool)

    # ------------------------------------------------------------ arrays (views, read them)
    points = property(lambda self: self._points.data, doc="(M, 3) float64; rows may be adjusted in place")
    colors = property(lambda self: self._colors.data, doc="(M, 3) uint8 RGB")
    alive = property(lambda self: self._alive.data, doc="(M,) bool; a removed point keeps its row")
    obs_view = property(lambda self: self._obs_view.data, doc="(O,) int64")
    obs_feature = property(lambda self: self._obs_feature.data, doc="(O,) int64")
    obs_point = property(lambda self: self._obs_point.data, doc="(O,) int64")
    obs_linked = property(lambda self: self._obs_linked.data, doc="(O,) bool: the interest point stands for it")

    # ------------------------------------------------------------ building
    def add_points(self, points: np.ndarray, colors: np.ndarray) -> np.ndarray:
        """Append points (K, 3) with colours (K, 3); returns their ids (K,)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        ids = np.arange(self._points.n, self._points.n + len(points))
        self._points.extend(points)
        self._colors.extend(np.asarray(colors, np.uint8).reshape(-1, 3))
        self._alive.extend(np.ones(len(points), bool))
        return ids

    def add_observations(self, view: int, features: np.ndarray, point_ids: np.ndarray, link: bool = True) -> None:
        """Record that ``features`` (K,) of ``view`` observe ``point_ids`` (K,).

        link: the interest points now stand for those points (``point_of_feature``); False
        records an observation for the cost only (the paper mode's chained points)."""
        features = np.asarray(features, np.int64)
        point_ids = np.asarray(point_ids, np.int64)
        self._obs_view.extend(np.full(len(features), view, np.int64))
        self._obs_feature.extend(features)
        self._obs_point.extend(point_ids)
        self._obs_linked.extend(np.full(len(features), link, bool))
        if link:
            self.views[view].point_of_feature[features] = point_ids

    def remove_observations(self, mask: np.ndarray) -> None:
        """Drop the observations selected by mask (O,) and unlink their interest points."""
        removed = np.flatnonzero(mask)
        for v, rows in _rows_by_value(self.obs_view[removed]):
            sel = removed[rows]
            pof = self.views[v].point_of_feature
            f = self.obs_feature[sel]
            linked = pof[f] == self.obs_point[sel]
            pof[f[linked]] = -1
        keep = ~mask
        for arr in (self._obs_view, self._obs_feature, self._obs_point, self._obs_linked):
            arr.keep(keep)

    def remove_points(self, point_ids: np.ndarray) -> None:
        """Mark points dead and drop their observations."""
        point_ids = np.asarray(point_ids, np.int64)
        if len(point_ids) == 0:
            return
        self.alive[point_ids] = False
        self.remove_observations(~self.alive[self.obs_point])

    def remove_lonely_points(self) -> None:
        """Points seen fewer than twice are no points."""
        self.remove_points(np.flatnonzero(self.alive & (self.track_lengths() < 2)))

    def filter_observations(self, bad: np.ndarray) -> int:
        """Drop the observations selected by ``bad`` (O,) bool (outliers), then the points seen
        fewer than twice. Returns the number of observations dropped."""
        self.remove_observations(bad)
        self.remove_lonely_points()
        return int(bad.sum())

    def merge_points(self, keep: np.ndarray, drop: np.ndarray) -> int:
        """Merge point ``drop[i]`` into ``keep[i]``: its observations move over (unless a view
        already sees ``keep[i]``: then they are not the same point), it dies. Returns the
        number of merges done."""
        done = 0
        for p, q in zip(keep, drop):
            if p == q or not (self.alive[p] and self.alive[q]):
                continue
            obs_q = np.flatnonzero(self.obs_point == q)
            if np.isin(self.obs_view[obs_q], self.obs_view[self.obs_point == p]).any():
                continue
            self.obs_point[obs_q] = p
            for o in obs_q:
                if self.obs_linked[o]:
                    self.views[self.obs_view[o]].point_of_feature[self.obs_feature[o]] = p
            self.alive[q] = False
            done += 1
        return done

    def deregister(self, view: int) -> None:
        """Forget a view's camera and observations, and the points no longer seen twice (its
        interest points stay: they describe the image). The view's status becomes "pending"."""
        self.remove_observations(self.obs_view == view)
        self.remove_lonely_points()
        v = self.views[view]
        v.P, v.camera_model, v.zoomed, v.status, v.found_by = None, None, False, "pending", None
        v.registration_flag = v.flag_reason = None  # what its registration said of the camera it no longer has
        v.point_of_feature[:] = -1

    def checkpoint(self, copy: bool = True) -> Checkpoint:
        """Everything an insertion may change (points, observations, views). ``copy`` False
        gives views of the current arrays, for a state written out at once (pickled), not kept."""
        arrays = (self.points, self.colors, self.alive, self.obs_view, self.obs_feature, self.obs_point,
                  self.obs_linked)
        if copy:
            arrays = tuple(a.copy() for a in arrays)
        return Checkpoint(*arrays[:3], arrays[3:], tuple(v._state() for v in self.views))

    def restore(self, state: Checkpoint) -> None:
        """Back to the state of ``state`` (from :meth:`checkpoint`)."""
        self._points.set(state.points)
        self._colors.set(state.colors)
        self._alive.set(state.alive)
        for arr, values in zip((self._obs_view, self._obs_feature, self._obs_point, self._obs_linked),
                               state.observations):
            arr.set(values)
        for v, s in zip(self.views, state.views):
            v._restore(s)

    # ------------------------------------------------------------ queries
    def observation_xy(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Pixels (O, 2) of the observations (optionally a subset)."""
        views = self.obs_view if mask is None else self.obs_view[mask]
        feats = self.obs_feature if mask is None else self.obs_feature[mask]
        out = np.empty((len(views), 2))
        for v, rows in _rows_by_value(views):
            out[rows] = self.views[v].features.points[feats[rows]]
        return out

    def observation_errors(self, mask: np.ndarray | None = None) -> np.ndarray:
        """Reprojection distance (px) of every observation, (O,), or of those of ``mask`` (O,) bool."""
        no_camera = np.full((3, 4), np.nan)
        Ps = np.stack([no_camera if v.P is None else v.P for v in self.views]) if self.views else no_camera[None]
        if mask is None:
            return observation_errors(Ps, self.points, self.obs_view, self.obs_point, self.observation_xy())
        return observation_errors(Ps, self.points, self.obs_view[mask], self.obs_point[mask], self.observation_xy(mask))

    def shared_pixels(self, a: int, b: int) -> np.ndarray:
        """(S, 4) float64 (xa, ya, xb, yb): the pixels in views a and b of the points both
        observe (a point's first observation in each view): the seeds of a pair's propagation."""
        rows = []
        for v in (a, b):
            sel = self.obs_view == v
            rows.append((self.obs_point[sel], self.views[v].features.points[self.obs_feature[sel]]))
        _, ia, ib = np.intersect1d(rows[0][0], rows[1][0], return_indices=True)
        return np.hstack([rows[0][1][ia], rows[1][1][ib]])

    def track_lengths(self) -> np.ndarray:
        return np.bincount(self.obs_point, minlength=len(self.points))

    def points_seen_by(self, view: int) -> np.ndarray:
        """Ids of the live points view ``view`` observes, (K,) in observation order."""
        sel = (self.obs_view == view) & self.alive[self.obs_point]
        return self.obs_point[sel]

    @property
    def registered_views(self) -> list[int]:
        return [i for i, v in enumerate(self.views) if v.registered]

    def registered_before(self, k: int, count: int) -> list[int]:
        """The last ``count`` registered views before view k, nearest first."""
        return [i for i in range(k - 1, -1, -1) if self.views[i].registered][:count]

    def reference_K(self, view: int) -> np.ndarray:
        """The calibrated second camera's K, the reference of the constrained camera models, in
        view ``view``'s image frame (a view turned by 180 degrees keeps the unturned principal
        point, now at (W - 1 - cx, H - 1 - cy)). On a rig walk, the calibrated camera of the
        view's side (left: view 0's, right: view 1's)."""
        source = self.views[view % 2 if self.rig is not None else 1]
        return self.views[view].in_frame_of(source.K, source)

    def live_points(self) -> tuple[np.ndarray, np.ndarray]:
        """(points (K, 3), colours (K, 3)) of the points still alive and observed."""
        keep = self.alive & (self.track_lengths() >= 2)
        return self.points[keep], self.colors[keep]

    def reprojection_summary(self) -> dict[str, float]:
        """RMS (px) over observations and the paper's eq. 14 over the registered images and the
        observed points."""
        if len(self.obs_view) == 0:
            return {"rms_px": float("nan"), "eq14": float("nan"), "observations": 0}
        err = self.observation_errors()
        n_pts = int(np.sum(self.alive & (self.track_lengths() > 0)))
        return {"rms_px": float(np.sqrt(np.mean(err ** 2))),
                "eq14": eq14(float(np.sum(err ** 2)), len(self.registered_views), n_pts),
                "observations": int(len(err))}
