"""Checkpoints of a run, so that an interrupted run can resume (``reconstruct --resume``).

After each insertion the reconstruction's whole state (points, observations, every view's
camera, interest points and links; not the images, which are read again) and the per-image
reports are pickled atomically. A checkpoint belongs to one set of inputs (image pixels, the
pair's cameras, the configuration: :func:`inputs_key`); a resumed run continues exactly where
the interrupted one stopped and gives the same result as an uninterrupted run (every step is
deterministic, and the correspondence source's caches only save time).
"""
from __future__ import annotations

import hashlib
import json
import logging
import pickle
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .config import Config
from .features import Features, to_gray
from .io import atomic_path
from .reconstruction import Checkpoint, Reconstruction, View

__all__ = ["inputs_key", "save_checkpoint", "load_checkpoint"]

log = logging.getLogger(__name__)
VERSION = 1


def inputs_key(images: list[np.ndarray], names: list[str], P_pair: list[np.ndarray], cfg: Config) -> str:
    """A digest of everything that decides a run's result."""
    h = hashlib.sha256()
    for name, image in zip(names, images):
        h.update(name.encode("utf-8"))
        h.update(str(image.shape).encode())
        h.update(np.ascontiguousarray(image).tobytes())
    for P in P_pair:
        h.update(np.asarray(P, np.float64).tobytes())
    h.update(json.dumps(cfg.to_dict(), sort_keys=True).encode())
    return h.hexdigest()


def _features_state(f: Features | None) -> tuple | None:
    return None if f is None else (f.points, f.desc, f.valid, f.response, f.image_shape)


def save_checkpoint(path: str | Path, recon: Reconstruction, per_image: list[dict[str, Any]], key: str) -> None:
    """Pickle the reconstruction's state and the reports so far to ``path`` (atomically)."""
    state = recon.checkpoint(copy=False)  # pickled at once: no copy needed
    # (P, features, point_of_feature, image, status, rotated_180, camera_model, zoomed) per view;
    # the images are read again on resume, the grey images recomputed from them
    views = [(s[0], _features_state(s[1]), s[2], None) + tuple(s[4:8]) for s in state.views]
    payload = {"version": VERSION, "key": key, "per_image": per_image, "points": state.points, "colors": state.colors,
               "alive": state.alive, "observations": state.observations, "views": views}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            pickle.dump(payload, fh, protocol=pickle.HIGHEST_PROTOCOL)


def load_checkpoint(path: str | Path, images: list[np.ndarray], names: list[str], key: str, source: Any
                    ) -> tuple[Reconstruction, list[dict[str, Any]]] | None:
    """The reconstruction and reports saved at ``path`` for these inputs (``key``), with the
    images put back (turned where the run turned them) and ``source`` as correspondence source;
    None when there is no usable checkpoint (missing, another version, other inputs)."""
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
    for name, image, s in zip(names, images, payload["views"]):
        P, feats, pof, _, status, rotated, model, zoomed = s
        image = cv2.rotate(image, cv2.ROTATE_180) if rotated else image
        features = None if feats is None else Features(*feats, gray=to_gray(image))
        views.append(View(name, image=image))
        states.append((P, features, pof, image, status, rotated, model, zoomed, False))
    recon = Reconstruction(views)
    recon.restore(Checkpoint(payload["points"], payload["colors"], payload["alive"], payload["observations"],
                             tuple(states)))
    recon.source = source
    return recon, payload["per_image"]
