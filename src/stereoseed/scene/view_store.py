"""Where a view's pixels and descriptors live while a long walk runs: held, let go (the grey image
computed again from the image when needed) or spilled to a file and memory-mapped. The
reconstruction stays data (:mod:`stereoseed.scene.reconstruction`); this module does the disk.

A view out of the mapper's working set keeps only its points in memory, and a page of its
descriptors is read back only if an old view is matched again, so the memory of a long run
grows with its points and observations only.
"""
from __future__ import annotations

import uuid
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.config import Config
from stereoseed.io.files import atomic_path
from stereoseed.io.sequence import ImageSequence
from stereoseed.scene.reconstruction import Reconstruction, View

__all__ = ["view_of_input", "release_pixels", "working_set", "release_old_views"]


def view_of_input(name: str, images: Sequence[np.ndarray], index: int) -> View:
    """The view of input image ``index``: read when needed from an :class:`ImageSequence` (not
    held), held from a plain list."""
    if isinstance(images, ImageSequence):
        return View(name, load=partial(images.__getitem__, index))
    return View(name, image=images[index])


def release_pixels(view: View, spill_to: Path | None = None) -> None:
    """Let go of the view's grey image and, with ``spill_to`` (a folder), move its descriptors to
    a file there, memory-mapped."""
    f = view.features
    if f is None:
        return
    changes: dict[str, Any] = {}
    if f.gray is not None and view.can_read_image_again:
        changes["gray"] = None
    # a memory map backed by a file (a restored checkpoint's arrays are in RAM)
    if spill_to is not None and getattr(f.desc, "filename", None) is None and f.desc.size:
        path = Path(spill_to) / f"desc_{uuid.uuid4().hex}.npy"  # unique across runs: a resumed run spills beside
        with atomic_path(path) as tmp:  # a checkpoint may name it: never half written
            np.save(tmp, f.desc)
        changes["desc"] = np.load(path, mmap_mode="r")
    view.replace_features(**changes)


def working_set(recon: Reconstruction, cfg: Config) -> set[int]:
    """The views whose pixels and descriptors the next insertions and the loop closure use: the
    BA window, the motion prior's recent views, the two before the next image, and the first
    views (the loop closure matches them at the end)."""
    reg = recon.registered_views
    working = max(cfg.pipeline.window, cfg.motion_prior.recent_views) + 2
    return set(reg[:cfg.loop_closure.span]) | set(reg[-working:])


def release_old_views(recon: Reconstruction, cfg: Config, spill_to: Path) -> None:
    """:func:`release_pixels` of every registered view outside the :func:`working_set`."""
    keep = working_set(recon, cfg)
    for i in recon.registered_views:
        if i not in keep:
            release_pixels(recon.views[i], spill_to)
