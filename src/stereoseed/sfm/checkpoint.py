"""Checkpoints of a run, so that an interrupted run can resume (``reconstruct --resume``).

After each insertion the reconstruction's whole state (points, observations, every view's
camera, interest points and links; not the images, which are read again) and the per-image
reports are pickled atomically. The descriptors of a view out of the mapper's working set are
written once, when it leaves it, to the folder beside the checkpoint (:func:`spill_folder`), and
the checkpoint names their file: a checkpoint costs the working set and the model, not the
whole sequence's descriptors (300 MB at 300 images). A checkpoint belongs to one set of inputs (image pixels, the
pair's cameras, the configuration: :func:`inputs_key`); a resumed run continues exactly where
the interrupted one stopped and gives the same result as an uninterrupted run (every step is
deterministic, and the correspondence source's caches only save time).
"""
from __future__ import annotations

import hashlib
import os
import json
import logging
import pickle
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stereoseed.config import Config
from stereoseed.features.harris import Features
from stereoseed.io.files import atomic_path
from stereoseed.sfm.reconstruction import Checkpoint, Reconstruction, View
from stereoseed.io.sequence import ImageSequence

__all__ = ["inputs_key", "save_checkpoint", "CheckpointWriter", "load_checkpoint", "spill_folder", "SPILL_SUFFIX"]

log = logging.getLogger(__name__)
VERSION = 2  # 2: spilled descriptors named, not copied
SPILL_SUFFIX = ".spill"  # the spill folder: the checkpoint's name with this added


def spill_folder(checkpoint: str | Path) -> Path:
    """The folder beside ``checkpoint`` where the run spills the descriptors of old views
    (:meth:`stereoseed.sfm.reconstruction.View.release_pixels`); the checkpoint refers to them."""
    checkpoint = Path(os.path.abspath(checkpoint))  # normalised as a memory map's file name is
    return checkpoint.with_name(checkpoint.name + SPILL_SUFFIX)


def inputs_key(images: Sequence[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config) -> str:
    """A digest of everything that decides a run's result (an :class:`ImageSequence` by its
    files, not decoded)."""
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
    return h.hexdigest()


def _features_state(f: Features | None, spilled_in: Path) -> tuple | None:
    """What a checkpoint holds of a view's interest points: descriptors spilled to
    ``spilled_in`` by their file name, ("spilled", name), the rest as arrays."""
    if f is None:
        return None
    desc = f.desc
    filename = getattr(desc, "filename", None)  # a memory map's file
    if filename is not None and Path(filename).parent == spilled_in:
        desc = ("spilled", Path(filename).name)
    return (f.points, desc, f.valid, f.response, f.image_shape)


def _checkpoint_bytes(path: str | Path, recon: Reconstruction, per_image: list[dict[str, Any]], key: str) -> bytes:
    """The pickled checkpoint of the reconstruction's state and the reports so far (a snapshot:
    the run may go on changing ``recon``)."""
    state = recon.checkpoint(copy=False)  # pickled at once: no copy needed
    # (P, features, point_of_feature, image, status, rotated_180, camera_model, zoomed) per view;
    # the images are read again on resume, the grey images recomputed from them
    spilled_in = spill_folder(path)
    views = [(s[0], _features_state(s[1], spilled_in), s[2], None) + tuple(s[4:8]) for s in state.views]
    payload = {"version": VERSION, "key": key, "per_image": per_image, "points": state.points, "colors": state.colors,
               "alive": state.alive, "observations": state.observations, "views": views}
    return pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)


def _write(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def save_checkpoint(path: str | Path, recon: Reconstruction, per_image: list[dict[str, Any]], key: str) -> None:
    """Pickle the reconstruction's state and the reports so far to ``path`` (atomically)."""
    _write(path, _checkpoint_bytes(path, recon, per_image, key))


class CheckpointWriter:
    """Checkpoints saved while the run goes on: :meth:`save` pickles the state at once (a
    consistent snapshot) and a thread writes it and puts it in place (atomically: the previous
    checkpoint stays whole until then) while the next insertion runs; writing and replacing a
    file of megabytes takes milliseconds of the disk's time, not the run's. Each save first
    waits for the previous one. Use as a context manager: leaving it waits for the last write;
    a failed write raises (at the next save or on leaving). ``path`` None: a run without
    checkpoints, every save does nothing."""

    def __init__(self, path: str | Path | None, key: str):
        self.path, self.key = path, key
        self._executor = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereoseed-checkpoint")
                          if path is not None else None)
        self._pending: Future | None = None

    def _wait(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def save(self, recon: Reconstruction, per_image: list[dict[str, Any]]) -> None:
        if self._executor is None:
            return
        data = _checkpoint_bytes(self.path, recon, per_image, self.key)
        self._wait()
        self._pending = self._executor.submit(_write, self.path, data)

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


def load_checkpoint(path: str | Path, images: Sequence[np.ndarray], names: list[str], key: str, source: Any
                    ) -> tuple[Reconstruction, list[dict[str, Any]]] | None:
    """The reconstruction and reports saved at ``path`` for these inputs (``key``), with the
    images put back (read when needed from an :class:`ImageSequence`, turned where the run
    turned them) and ``source`` as correspondence source; None when there is no usable
    checkpoint (missing, another version, other inputs, its spilled descriptors gone). The
    grey images are left to be computed again when needed (:meth:`View.restore_gray`)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            payload = pickle.load(fh)
    except FileNotFoundError:
        return None
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ValueError) as e:
        log.warning("%s: unreadable checkpoint (%s); starting again", path, e)
        return None
    if not isinstance(payload, dict) or payload.get("version") != VERSION or payload.get("key") != key:
        log.warning("%s: the checkpoint is of other inputs or settings; starting again", path)
        return None
    views, states = [], []
    lazy, spilled_in = isinstance(images, ImageSequence), spill_folder(path)
    try:
        for i, (name, s) in enumerate(zip(names, payload["views"])):
            P, feats, pof, _, status, rotated, model, zoomed = s
            view = View.of_input(name, images, i)
            image = cv2.rotate(view.image, cv2.ROTATE_180) if rotated else (None if lazy else images[i])
            features = None if feats is None else _features(feats, spilled_in)
            views.append(view)
            states.append((P, features, pof, image, status, rotated, model, zoomed, features is not None))
    except (OSError, ValueError, EOFError) as e:  # missing, truncated or empty
        log.warning("%s: the checkpoint's spilled descriptors cannot be read (%s); starting again", path, e)
        return None
    recon = Reconstruction(views)
    recon.restore(Checkpoint(payload["points"], payload["colors"], payload["alive"], payload["observations"],
                             tuple(states)))
    recon.source = source
    return recon, payload["per_image"]


def _features(state: tuple, spilled_in: Path) -> Features:
    """A view's interest points from their checkpoint state, spilled descriptors memory-mapped."""
    points, desc, valid, response, image_shape = state
    if isinstance(desc, tuple):
        desc = np.load(spilled_in / desc[1], mmap_mode="r")
    return Features(points, desc, valid, response, image_shape, gray=None)
