"""Checkpoints of a run, so that an interrupted run can resume (``reconstruct --resume``).

After each insertion the reconstruction's whole state (points, observations, every view's
camera, interest points, links and history, from which the per-image reports are rendered; not
the images, which are read again) is written atomically. The descriptors of a view out of the mapper's working set are
written once, when it leaves it, to the folder beside the checkpoint (:func:`spill_folder`), and
the checkpoint names their file: a checkpoint costs the working set and the model, not the
whole sequence's descriptors (300 MB at 300 images). A checkpoint belongs to one set of inputs (image pixels, the
pair's cameras, the configuration: :func:`inputs_key`); a resumed run continues exactly where
the interrupted one stopped and gives the same result as an uninterrupted run (every step is
deterministic, and the correspondence source's caches only save time).

The file holds data only, never code: an uncompressed ``.npz`` of NumPy arrays (read with
``allow_pickle=False``) whose member ``meta`` is UTF-8 JSON (the version, the inputs' key, each
view's flags and the events of its history) and whose member ``mac`` is an HMAC-SHA256 of all the others keyed
by the inputs' key. A checkpoint is used only when it and its folders belong to the user and
nobody else may write them, its signature matches, and every array has the dtype, shape and
index range the model needs; anything else is logged and the run starts again.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import logging
import math
import os
import stat
import tempfile
import zipfile
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.features.harris import Features
from stereoseed.io.atomic import jsonable
from stereoseed.io.sequence import ImageSequence
from stereoseed.scene.camera_life import event_from_json, event_to_json
from stereoseed.scene.reconstruction import Checkpoint, Reconstruction
from stereoseed.scene.view_store import view_of_input

__all__ = ["inputs_key", "save_checkpoint", "CheckpointWriter", "load_checkpoint", "checkpoint_header", "spill_folder",
           "SPILL_SUFFIX"]

log = logging.getLogger(__name__)
# 3: arrays and JSON in a signed npz; spilled descriptors named, not copied; 4: registration flags;
# 5: each view's history (status, flags and reports rendered from it), the model before a doubted insertion
VERSION = 5
SPILL_SUFFIX = ".spill"  # the spill folder: the checkpoint's name with this added
_META, _MAC = "meta", "mac"
_OBSERVATIONS = ("obs_view", "obs_feature", "obs_point", "obs_linked")  # Checkpoint.observations' order
_VIEW_FLAGS = {"name": str, "rotated_180": bool, "camera_model": (str, type(None)),
               "zoomed": bool, "registered": bool, "features": bool, "desc_file": (str, type(None)),
               "features_as_now": bool, "history": list}
_UNDO = "undo."  # the prefix of the model before the last insertion (Reconstruction.insertion_undo)
_FLOAT = "float"  # an expected dtype: float32 or float64, native byte order


class _Refused(Exception):
    """A checkpoint that must not be used; the message says why."""


# what reading a file from outside may raise, whatever it holds: the run starts again
_UNUSABLE = (_Refused, OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, NotImplementedError,
             MemoryError, OverflowError, RecursionError)


def spill_folder(checkpoint: str | Path) -> Path:
    """The folder beside ``checkpoint`` where the run spills the descriptors of old views
    (:func:`stereoseed.scene.view_store.release_pixels`); the checkpoint refers to them."""
    checkpoint = Path(os.path.abspath(checkpoint))  # normalised as a memory map's file name is
    return checkpoint.with_name(checkpoint.name + SPILL_SUFFIX)


def inputs_key(images: Sequence[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config,
               rig: bool = False) -> str:
    """A digest of everything that decides a run's result (an :class:`ImageSequence` by its
    files, not decoded; a rig walk's marked "+rig")."""
    h = hashlib.sha256()
    for name in names:
        h.update(name.encode("utf-8"))
    if isinstance(images, ImageSequence):
        h.update(images.fingerprint())
    else:
        for image in images:
            h.update(str(image.shape).encode())
            h.update(np.ascontiguousarray(image).tobytes())
    for P in P_pair:
        h.update(np.asarray(P, np.float64).tobytes())
    h.update(json.dumps(cfg.to_dict(), sort_keys=True).encode())
    return h.hexdigest() + ("+rig" if rig else "")


# ---------------------------------------------------------------------------------- writing
def _spilled_name(desc: np.ndarray, spilled_in: Path) -> str | None:
    """The file name of descriptors memory-mapped from ``spilled_in``, else None."""
    filename = getattr(desc, "filename", None)  # a memory map's file
    if filename is not None and Path(filename).parent == spilled_in:
        return Path(filename).name
    return None


def _state_arrays(state: Checkpoint, names: list[str], spilled_in: Path, prefix: str = "",
                  now: Checkpoint | None = None) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """The arrays and view descriptions of a model's ``state`` (a :class:`Checkpoint`), named
    with ``prefix``. now: the state beside which ``state`` is kept (the model before the last
    insertion): a view whose interest points are the very ones it has now says so
    ("features_as_now") rather than writing them twice."""
    arrays = {f"{prefix}points": state.points.copy(), f"{prefix}colors": state.colors.copy(),
              f"{prefix}alive": state.alive.copy()}
    arrays.update((f"{prefix}{name}", a.copy()) for name, a in zip(_OBSERVATIONS, state.observations))
    views = []
    for i, (name, s) in enumerate(zip(names, state.views)):
        P, features, point_of_feature, _, rotated, model, zoomed, _, history = s
        as_now = now is not None and features is not None and features is now.views[i][1]
        flags = {"name": name, "rotated_180": bool(rotated),
                 "camera_model": None if model is None else str(getattr(model, "value", model)), "zoomed": bool(zoomed),
                 "registered": P is not None, "features": features is not None, "desc_file": None,
                 "features_as_now": as_now,
                 # its status, what placed it, its flags and its report: a resumed run must not
                 # lose what was judged once, at registration
                 "history": [event_to_json(e) for e in history]}
        view = f"{prefix}view{i}"
        if P is not None:
            arrays[f"{view}.P"] = np.array(P, np.float64)
        arrays[f"{view}.point_of_feature"] = np.array(point_of_feature)
        if features is not None and not as_now:
            flags["desc_file"] = _spilled_name(features.desc, spilled_in)
            if flags["desc_file"] is None:
                arrays[f"{view}.desc"] = features.desc
            arrays[f"{view}.points"] = features.points
            arrays[f"{view}.valid"] = features.valid
            arrays[f"{view}.response"] = features.response
            arrays[f"{view}.image_shape"] = np.asarray(features.image_shape, np.int64)
        views.append(flags)
    return arrays, views


def _snapshot(path: str | Path, recon: Reconstruction, key: str) -> dict[str, np.ndarray]:
    """The checkpoint's arrays, the JSON part among them, as they are now: the arrays the run
    changes in place (points, observations, links) are copied; interest points are shared, as
    Features are replaced, never changed in place. The images are read again on resume, the
    grey images recomputed from them. The model as it was before the last insertion, while the
    run keeps it (``Reconstruction.insertion_undo``), is saved beside it under ``undo.``: a
    resumed run withdraws a doubted view as the uninterrupted one would."""
    state = recon.checkpoint(copy=False)
    spilled_in = spill_folder(path)
    names = [v.name for v in recon.views]
    arrays, views = _state_arrays(state, names, spilled_in)
    undo = None
    if recon.insertion_undo is not None:
        k, before = recon.insertion_undo
        more, undo_views = _state_arrays(before, names, spilled_in, _UNDO, now=state)
        arrays.update(more)
        undo = {"view": int(k), "views": undo_views}
    meta = {"version": VERSION, "key": key, "views": views, "insertion_undo": undo}
    arrays[_META] = np.frombuffer(json.dumps(meta, default=jsonable).encode("utf-8"), np.uint8)
    return arrays


def _signature(arrays: dict[str, np.ndarray], key: str) -> np.ndarray:
    """HMAC-SHA256 keyed by the inputs' key of every array but the signature (name, dtype,
    shape and bytes, in name order): (32,) uint8."""
    mac = hmac.new(key.encode("utf-8"), digestmod=hashlib.sha256)
    for name in sorted(arrays):
        if name == _MAC:
            continue
        a = np.ascontiguousarray(arrays[name])
        head = json.dumps([name, a.dtype.str, list(a.shape)]).encode("utf-8")
        mac.update(len(head).to_bytes(8, "little"))
        mac.update(head)
        mac.update(a.reshape(-1).view(np.uint8))
    return np.frombuffer(mac.digest(), np.uint8)


def _write(path: str | Path, arrays: dict[str, np.ndarray], key: str) -> None:
    """Sign ``arrays`` and write them to ``path`` atomically, readable and writable by the user
    alone (a checkpoint others may write is refused on resume)."""
    path = Path(path)
    signed = dict(arrays)
    signed[_MAC] = _signature(arrays, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)  # mode 0600
        try:
            with os.fdopen(fd, "wb") as fh:  # a file object: np.savez would add ".npz" to a name
                np.savez(fh, allow_pickle=False, **signed)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:
        raise StereoseedError(f"{path}: cannot write ({e.strerror or e})") from None


def save_checkpoint(path: str | Path, recon: Reconstruction, key: str) -> None:
    """Write the reconstruction's state (its views' histories included) to ``path`` (atomically)."""
    _write(path, _snapshot(path, recon, key), key)


class CheckpointWriter:
    """Checkpoints saved while the run goes on: :meth:`save` takes a snapshot of the state at
    once (a consistent one) and a thread signs it, writes it and puts it in place (atomically:
    the previous checkpoint stays whole until then) while the next insertion runs; writing and
    replacing a file of megabytes takes milliseconds of the disk's time, not the run's. Each
    save first waits for the previous one. Use as a context manager: leaving it waits for the
    last write; a failed write raises (at the next save or on leaving). ``path`` None: a run
    without checkpoints, every save does nothing."""

    def __init__(self, path: str | Path | None, key: str):
        self.path, self.key = path, key
        self._executor = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereoseed-checkpoint")
                          if path is not None else None)
        self._pending: Future | None = None

    def _wait(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def save(self, recon: Reconstruction) -> None:
        if self._executor is None:
            return
        arrays = _snapshot(self.path, recon, self.key)
        self._wait()
        self._pending = self._executor.submit(_write, self.path, arrays, self.key)

    def __enter__(self) -> CheckpointWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            self._wait()
        except Exception as write_error:
            if exc is None:
                raise
            # the run's own error is the one to report; the last checkpoint stays whole
            log.warning("%s: the last checkpoint was not written (%s)", self.path, write_error)
        finally:
            if self._executor is not None:
                self._executor.shutdown()


# ---------------------------------------------------------------------------------- reading
def _check_owner(st: os.stat_result, path: Path) -> None:
    """Refuse a file or folder of another user's, or one that group or others may write: whoever
    can write it could have planted the checkpoint. Not checked where there are no uids."""
    if not hasattr(os, "getuid"):
        return
    if st.st_uid != os.getuid():
        raise _Refused(f"{path} belongs to another user")
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise _Refused(f"{path} may be written by group or others")


def _checked_members(zf: zipfile.ZipFile) -> dict[str, str]:
    """{array name: member name}, once every member is seen to be a stored (uncompressed)
    ``.npy`` of plain numbers whose header claims no more data than the member holds."""
    members = {info.filename[:-len(".npy")]: info.filename for info in zf.infolist()}
    if len(members) != len(zf.infolist()):
        raise _Refused("an array is stored twice")
    for info in zf.infolist():
        if (info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size
                or not info.filename.endswith(".npy")):
            raise _Refused(f"an unexpected member {info.filename!r}")
        with zf.open(info) as member:
            version = np.lib.format.read_magic(member)
            if version not in ((1, 0), (2, 0)):
                raise _Refused(f"{info.filename!r} is of an unknown .npy version")
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, _, dtype = read_header(member)
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
            raise _Refused(f"{info.filename!r} holds objects, not numbers")
        if math.prod(shape) * dtype.itemsize > info.file_size:
            raise _Refused(f"{info.filename!r} is shorter than its shape")
    return members


def _read(path: Path, key: str) -> dict[str, np.ndarray]:
    """The checkpoint's arrays once its owner, permissions, container and signature are checked
    (the signature before any of them is interpreted). FileNotFoundError when there is none."""
    arrays = _checked_arrays(path)
    mac = arrays.pop(_MAC, None)
    if (mac is None or mac.dtype != np.uint8 or mac.shape != (32,)
            or not hmac.compare_digest(mac.tobytes(), _signature(arrays, key).tobytes())):
        raise _Refused("its signature does not match these inputs (another run's, or altered)")
    return arrays


def checkpoint_header(path: str | Path) -> tuple[int, str] | None:
    """(how many views, the inputs' key) a checkpoint says it holds, read under the same checks of
    its owner, permissions and container as :func:`load_checkpoint` (its signature cannot be
    checked before the key is known: :func:`load_checkpoint` checks it). None without a usable
    one (a warning unless there is none): for a caller that must know which inputs to sign for
    (a live run stopped while finishing was signed for ``reconstruct``'s)."""
    path = Path(path)
    try:
        raw = _checked_arrays(path, only=_META)[_META]
        meta = json.loads(raw.tobytes().decode("utf-8"))
        return len(meta["views"]), str(meta["key"])
    except FileNotFoundError:
        return None
    except (*_UNUSABLE, TypeError, UnicodeDecodeError) as e:
        log.warning("%s: unusable checkpoint (%s)", path, e)
        return None


def _checked_arrays(path: Path, only: str | None = None) -> dict[str, np.ndarray]:
    """The checkpoint's arrays (``only``: that member alone), unsigned, once its owner,
    permissions and container are checked."""
    # non-blocking: a FIFO planted as the checkpoint would otherwise wait for a writer forever;
    # a regular file reads as usual (the flag only matters for the open)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
                 | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())  # the file opened, not whatever the name points to later
        if not stat.S_ISREG(st.st_mode):
            raise _Refused("not a file")
        _check_owner(st, path)
        _check_owner(os.stat(path.parent), path.parent)
        loaded = np.load(fh, allow_pickle=False)  # a pickle raises ValueError, unread
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise _Refused("not an .npz archive")
        with loaded as npz:
            # read by member name: NpzFile would take "a.npy" for member "a.npy", not "a.npy.npy"
            members = _checked_members(npz.zip)
            if only is not None:
                if only not in members:
                    raise _Refused(f"no {only!r}")
                members = {only: members[only]}
            return {name: npz[member] for name, member in members.items()}


def _meta(arrays: dict[str, np.ndarray], key: str, names: list[str]) -> dict[str, Any]:
    """The JSON part, its version, key and view flags checked (the histories are read with the
    views)."""
    raw = arrays.pop(_META, None)
    if raw is None or raw.dtype != np.uint8 or raw.ndim != 1:
        raise _Refused("no description")
    meta = json.loads(raw.tobytes().decode("utf-8"))
    if not isinstance(meta, dict) or meta.get("version") != VERSION or meta.get("key") != key:
        raise _Refused("written by another version or for other inputs")
    views = meta.get("views")
    if not isinstance(views, list) or len(views) != len(names):
        raise _Refused("its views are not these images")
    _check_views(views, names, as_now_allowed=False)
    undo = meta.get("insertion_undo")
    if undo is not None:
        if (not isinstance(undo, dict) or undo.keys() != {"view", "views"} or type(undo["view"]) is not int
                or not 2 <= undo["view"] < len(names) or not isinstance(undo["views"], list)
                or len(undo["views"]) != len(names)):
            raise _Refused("the model before the last insertion is malformed")
        _check_views(undo["views"], names, as_now_allowed=True)
    return meta


def _check_views(views: list[Any], names: list[str], as_now_allowed: bool) -> None:
    for name, flags in zip(names, views):
        if (not isinstance(flags, dict) or flags.keys() != _VIEW_FLAGS.keys() or flags["name"] != name
                or any(not isinstance(flags[k], kind) for k, kind in _VIEW_FLAGS.items())
                or (flags["features_as_now"] and not as_now_allowed)):
            raise _Refused(f"the description of {name!r} is malformed")


def _take(arrays: dict[str, np.ndarray], name: str, dtype: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    """Array ``name`` removed from ``arrays``, refused unless of ``dtype`` and ``shape`` (None:
    any length)."""
    a = arrays.pop(name, None)
    if a is None:
        raise _Refused(f"{name} is missing")
    _check_array(a, name, dtype, shape)
    return a


def _check_array(a: np.ndarray, name: str, dtype: Any, shape: tuple[int | None, ...]) -> None:
    good_dtype = a.dtype in (np.float32, np.float64) if dtype == _FLOAT else a.dtype == np.dtype(dtype)
    if not good_dtype or a.ndim != len(shape) or any(s is not None and n != s for n, s in zip(a.shape, shape)):
        raise _Refused(f"{name} is {a.dtype} {a.shape}, not the expected array")


def _in_range(a: np.ndarray, low: int, high: int | np.ndarray, name: str) -> None:
    if a.size and not (np.all(a >= low) and np.all(a < high)):
        raise _Refused(f"{name} holds indices out of range")


def _spilled(name: str, folder: Path, n: int) -> np.ndarray:
    """Descriptors (n, D) memory-mapped from the file the checkpoint names in the spill folder."""
    if name in ("", ".", "..") or ".." in name or "/" in name or "\\" in name or "\0" in name \
            or Path(name).name != name:
        raise _Refused(f"the spilled descriptors' name {name!r} is not a file name")
    path = folder / name
    try:
        st = os.lstat(path)
    except OSError as e:
        raise _Refused(f"the spilled descriptors {name} cannot be read ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise _Refused(f"the spilled descriptors {name} are not a file")
    _check_owner(st, path)
    desc = np.load(path, mmap_mode="r", allow_pickle=False)
    if not isinstance(desc, np.ndarray):  # an .npz
        raise _Refused(f"the spilled descriptors {name} are not an array")
    _check_array(desc, name, _FLOAT, (n, None))
    return desc


def _model_points(arrays: dict[str, np.ndarray], prefix: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (M, 3), colours (M, 3), alive (M,)) checked (arrays named with ``prefix``)."""
    points = _take(arrays, f"{prefix}points", np.float64, (None, 3))
    m = len(points)
    return (points, _take(arrays, f"{prefix}colors", np.uint8, (m, 3)),
            _take(arrays, f"{prefix}alive", bool, (m,)))


def _model_state(arrays: dict[str, np.ndarray], views: list[dict[str, Any]], spilled_in: Path,
                 prefix: str = "", now: list[tuple] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, ...], list[tuple]]:
    """(points, colours, alive, observations, view states) of one saved state, checked."""
    points, colors, alive = _model_points(arrays, prefix)
    states = _view_states(arrays, views, spilled_in, len(points), prefix, now)
    return points, colors, alive, _observations(arrays, states, len(points), prefix), states


def _view_states(arrays: dict[str, np.ndarray], views: list[dict[str, Any]], spilled_in: Path, n_points: int,
                 prefix: str = "", now: list[tuple] | None = None) -> list[tuple]:
    """Each view's (P, Features or None, point_of_feature, rotated_180, camera_model, zoomed,
    history), every array and event checked (links to points below ``n_points``); arrays named
    with ``prefix``; ``now``: the states whose interest points a view "features_as_now" shares."""
    if any(flags["desc_file"] is not None for flags in views):
        _check_owner(os.stat(spilled_in), spilled_in)
    states = []
    for i, flags in enumerate(views):
        view = f"{prefix}view{i}"
        P = _take(arrays, f"{view}.P", np.float64, (3, 4)) if flags["registered"] else None
        features = None
        if flags["features_as_now"]:
            features = None if now is None or not flags["features"] else now[i][1]
            if features is None:
                raise _Refused(f"{view} says it shares interest points the model does not have")
        elif flags["features"]:
            points = _take(arrays, f"{view}.points", _FLOAT, (None, 2))
            n = len(points)
            if flags["desc_file"] is None:
                desc = _take(arrays, f"{view}.desc", _FLOAT, (n, None))
            else:
                desc = _spilled(flags["desc_file"], spilled_in, n)
            valid = _take(arrays, f"{view}.valid", bool, (n,))
            response = _take(arrays, f"{view}.response", _FLOAT, (n,))
            image_shape = _take(arrays, f"{view}.image_shape", np.int64, (2,))
            if np.any(image_shape <= 0):
                raise _Refused(f"{view}.image_shape is not an image's")
            features = Features(points, desc, valid, response, (int(image_shape[0]), int(image_shape[1])), gray=None)
        elif flags["desc_file"] is not None:
            raise _Refused(f"{view} names descriptors without interest points")
        pof = _take(arrays, f"{view}.point_of_feature", np.int64, (None if features is None else len(features),))
        _in_range(pof, -1, n_points, f"{view}.point_of_feature")
        history = tuple(event_from_json(e) for e in flags["history"])
        states.append((P, features, pof, flags["rotated_180"], flags["camera_model"], flags["zoomed"], history))
    return states


def _observations(arrays: dict[str, np.ndarray], states: list[tuple], n_points: int,
                  prefix: str = "") -> tuple[np.ndarray, ...]:
    """(obs_view, obs_feature, obs_point, obs_linked), each observation's view, interest point
    and point seen to exist (arrays named with ``prefix``)."""
    obs_view = _take(arrays, f"{prefix}obs_view", np.int64, (None,))
    o = len(obs_view)
    obs_feature = _take(arrays, f"{prefix}obs_feature", np.int64, (o,))
    obs_point = _take(arrays, f"{prefix}obs_point", np.int64, (o,))
    obs_linked = _take(arrays, f"{prefix}obs_linked", bool, (o,))
    _in_range(obs_view, 0, len(states), "obs_view")
    _in_range(obs_point, 0, n_points, "obs_point")
    # a view without interest points has none to observe with
    counts = np.array([0 if s[1] is None else len(s[1]) for s in states], np.int64)
    _in_range(obs_feature, 0, counts[obs_view], "obs_feature")
    return obs_view, obs_feature, obs_point, obs_linked


def load_checkpoint(path: str | Path, images: Sequence[np.ndarray], names: list[str], key: str
                    ) -> tuple[Reconstruction, list[dict[str, Any]]] | None:
    """The reconstruction and reports saved at ``path`` for these inputs (``key``), with the
    images put back (read when needed from an :class:`ImageSequence`, turned where the run
    turned them) and ``source`` as correspondence source; None when there is no usable
    checkpoint (missing, another version, other inputs, another user's or writable by others,
    altered, malformed, its spilled descriptors gone), with a warning unless it is missing. The
    grey images are left to be computed again when needed (:meth:`View.restore_gray`)."""
    path = Path(path)
    spilled_in = spill_folder(path)
    try:
        arrays = _read(path, key)
    except FileNotFoundError:
        return None
    except _UNUSABLE as e:
        log.warning("%s: unusable checkpoint (%s); starting again", path, e)
        return None
    try:
        meta = _meta(arrays, key, names)
        *model, states = _model_state(arrays, meta["views"], spilled_in)
        undo = meta["insertion_undo"]
        if undo is not None:
            *before, before_states = _model_state(arrays, undo["views"], spilled_in, _UNDO, now=states)
        if arrays:
            raise _Refused(f"unexpected arrays ({', '.join(sorted(arrays)[:3])})")
        views = [view_of_input(name, images, i) for i, name in enumerate(names)]
        lazy = isinstance(images, ImageSequence)
        turned: dict[int, np.ndarray] = {}  # the images the run turned, read once

        def restored(view_states: list[tuple]) -> tuple[tuple, ...]:
            out = []
            for i, (P, features, pof, rotated, camera_model, zoomed, history) in enumerate(view_states):
                if rotated and i not in turned:
                    turned[i] = cv2.rotate(views[i].image, cv2.ROTATE_180)
                image = turned[i] if rotated else (None if lazy else images[i])
                out.append((P, features, pof, image, rotated, camera_model, zoomed, features is not None, history))
            return tuple(out)

        recon = Reconstruction(views)
        # the views check what only they know (a camera model's name, a camera's P)
        recon.restore(Checkpoint(*model[:3], model[3], restored(states)))
        if undo is not None:
            undo_state = Checkpoint(*before[:3], before[3], restored(before_states))
            now = recon.checkpoint()
            recon.restore(undo_state)  # checked as the model's own state is
            recon.restore(now)
            recon.insertion_undo = (undo["view"], undo_state)
        per_image = recon.reports()
        if not 2 <= len(per_image) or any(r.get("image") != names[i] for i, r in enumerate(per_image)):
            raise _Refused("its reports are not of these images")
    except _UNUSABLE as e:  # malformed, or its spilled descriptors gone
        log.warning("%s: unusable checkpoint (%s); starting again", path, e)
        return None
    return recon, per_image
