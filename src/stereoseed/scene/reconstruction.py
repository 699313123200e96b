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

It is also the only code that changes a camera's state (:mod:`stereoseed.scene.camera_life`):
:meth:`Reconstruction.calibrate`, :meth:`~Reconstruction.register`, :meth:`~Reconstruction.fail`,
:meth:`~Reconstruction.flag`, :meth:`~Reconstruction.lift_flag`, :meth:`~Reconstruction.judge`,
:meth:`~Reconstruction.withdraw`, :meth:`~Reconstruction.register_again` and
:meth:`~Reconstruction.drop`, each appending the event to the view's history.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Iterator

import numpy as np

from stereoseed.estimators.bundle import observation_errors
from stereoseed.features.harris import Features
from stereoseed.geometry.camera import Camera
from stereoseed.scene.camera_life import (Calibrated, Dropped, Failed, Flag, Flagged, FlagLifted, Inserted, Judged,
                                          Registered, RegisteredAgain, Stage, Status, Withdrawn, report_of)
from stereoseed.scene.view import View, intrinsics_in_frame

__all__ = ["View", "Reconstruction", "Checkpoint", "eq14", "intrinsics_in_frame"]


def eq14(sum_squared_px: float, n_images: int, n_points: int) -> float:
    """The paper's eq. 14: sum of squared reprojection errors over images x points (px^2, not
    rooted, as the paper prints it)."""
    return float(sum_squared_px / max(1, n_images * n_points))


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
        # (view k, the model just before k's insertion) while k, the last view placed, is doubted
        # (flagged when placed, or placed by the propagated matches alone): what withdrawing k
        # puts back (stereoseed.sfm.mapper); None otherwise
        self.insertion_undo: tuple[int, Checkpoint] | None = None

    def add_view(self, view: View) -> int:
        """One more view at the end, not reached yet (a live run learns its images one at a
        time): the model is then what it would be had the view been there from the start, the
        state kept before a doubted insertion (:attr:`insertion_undo`) included. Its index."""
        self.views.append(view)
        if self.insertion_undo is not None:
            k, before = self.insertion_undo
            fresh = tuple(v._state() for v in self.views[len(before.views):])
            self.insertion_undo = (k, replace(before, views=before.views + fresh))
        return len(self.views) - 1

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

    def _forget_camera(self, view: int) -> None:
        """A view's camera and observations gone, and the points no longer seen twice (its
        interest points stay: they describe the image)."""
        self.remove_observations(self.obs_view == view)
        self.remove_lonely_points()
        v = self.views[view]
        v.P, v.camera_model, v.zoomed = None, None, False
        v.point_of_feature[:] = -1

    # ------------------------------------------------------------ a camera's life
    def calibrate(self, view: int, P: np.ndarray) -> None:
        """View ``view`` is one of the calibrated pair, its camera P (3, 4)."""
        self.views[view].P = np.asarray(P, np.float64)
        self.views[view]._record(Calibrated())

    def register(self, view: int, camera: Camera, found_by: str, features: Features, image: np.ndarray,
                 rotated_180: bool, camera_model: str | None, zoomed: bool, flag: Flag | None = None) -> None:
        """Commit a registration: view ``view``'s ``camera`` (in the frame of ``image``, turned by
        180 degrees when ``rotated_180``), its interest points (none linked yet), the camera model
        it keeps when not the run's, whether it took a zoom, what placed it, and the flag its
        registration raised."""
        v = self.views[view]
        v.keep_image(image, rotated_180)
        v.features = features
        v.point_of_feature = np.full(len(features), -1, np.int64)
        v.camera_model = camera_model
        v.camera = camera
        v.zoomed = zoomed
        v._record(Registered(found_by))
        if flag is not None:
            v._record(Flagged(flag, Stage.PLACED))

    def record(self, view: int, report: dict[str, Any]) -> None:
        """View ``view``'s step of the run is done: ``report`` is what it did."""
        self.views[view]._record(Inserted(report))

    def fail(self, view: int, reason: str, report: dict[str, Any]) -> None:
        """View ``view`` could not be placed: ``reason``, and the attempt's ``report``."""
        v = self.views[view]
        if v.registered:
            raise ValueError(f"{v.name}: a placed camera is withdrawn or dropped, not failed")
        v._record(Failed(reason, report))

    def _placed(self, view: int) -> None:
        if self.views[view].life.status not in (Status.REGISTERED, Status.CALIBRATED):
            raise ValueError(f"{self.views[view].name}: {self.views[view].status}; only a placed camera has a flag")

    def flag(self, view: int, flag: Flag, stage: Stage = Stage.PLACED) -> None:
        """The run cannot vouch for view ``view``'s camera: ``flag``, raised at ``stage``."""
        self._placed(view)
        self.views[view]._record(Flagged(flag, stage))

    def lift_flag(self, view: int, why: str) -> None:
        """Later evidence (``why``) lifts view ``view``'s flag."""
        self._placed(view)
        self.views[view]._record(FlagLifted(why))

    def judge(self, view: int, flag: Flag | None) -> None:
        """The judgement after the last insertion: view ``view``'s final flag (None: vouched for)."""
        self._placed(view)
        self.views[view]._record(Judged(flag))

    def withdraw(self, view: int, reason: str, before: Checkpoint | None = None) -> None:
        """Take view ``view`` out of the model (``reason``): back to the model ``before`` its
        insertion when the run kept it (its points, the adjustments and outlier removals it
        caused: the model as it was), else its camera and observations only. Its interest points
        go too (as a view never placed); its history stays and says why."""
        v = self.views[view]
        if v.life.status != Status.REGISTERED:
            raise ValueError(f"{v.name}: {v.status}; only a registered camera is withdrawn")
        # the restore takes every view's history back to before the insertion: the withdrawn
        # view's, and the failures of the views tried after it since, which it must not erase
        # (they hold nothing of the model; erased, the run's report ended at the first of them)
        kept = {u: (w.history, w.life) for u, w in enumerate(self.views)
                if u == view or w.life.status == Status.FAILED}
        if before is not None:
            self.restore(before)
        else:
            self._forget_camera(view)
        v.features, v.point_of_feature = None, np.zeros(0, np.int64)
        for u, (history, life) in kept.items():
            self.views[u].history, self.views[u].life = history, life
        v._record(Withdrawn(reason))

    def register_again(self, view: int, found: str) -> None:
        """View ``view``'s camera is the one its neighbours found (``found`` says what and how;
        the caller moved it there): its flags are lifted, and it claims no zoom (a zoom its first
        camera claimed is no evidence for this one)."""
        self._placed(view)
        self.views[view].zoomed = False
        self.views[view]._record(RegisteredAgain(found))

    def drop(self, view: int, reason: str) -> None:
        """Take view ``view`` out at the end (``reason``): its camera and observations go."""
        self._placed(view)
        self._forget_camera(view)
        self.views[view]._record(Dropped(reason))

    def reports(self) -> list[dict[str, Any]]:
        """Each view's entry of the run's report, rendered from its history, for the views the run
        has reached (a prefix of the sequence)."""
        out = []
        for v in self.views:
            report = report_of(v.history)
            if report is None:
                break
            out.append(report)
        return out

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

    def shared_points(self, observations: np.ndarray):
        """(views, views) scipy sparse CSR: how many points two views both observe among
        ``observations`` (O,) bool (a view observing a point twice shares it once; a long walk's
        views see few others: sparse)."""
        from scipy import sparse

        seen = sparse.csr_matrix((np.ones(int(observations.sum())),
                                  (self.obs_view[observations], self.obs_point[observations])),
                                 shape=(len(self.views), len(self.points)))
        seen.data[:] = 1.0
        return (seen @ seen.T).tocsr()

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
