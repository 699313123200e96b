"""The ordered input images of a run, read when needed rather than all at once.

A walk filmed or photographed around an object has hundreds of images; the mapper works on the
last few (and the loop closure on the first few), so holding every decoded image would make the
memory grow with the sequence. :class:`ImageSequence` decodes an image when it is asked for and
keeps the most recently used ones (a small LRU, shared by the mapper and the thread that
prefetches interest points). It is a ``Sequence``: ``reconstruct`` takes it or a plain list.
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Callable, Union

import numpy as np

from stereoseed.io.files import read_image

__all__ = ["ImageSequence"]

Entry = Union[Path, np.ndarray]  # a file to read, or an image already in memory (a video keyframe)
Transform = Callable[[int, np.ndarray], np.ndarray]  # (index, image read) -> image the run uses


class ImageSequence(Sequence):
    """Images read from ``entries`` (paths, or arrays kept as they are) on demand, each passed
    through ``transform(index, image)`` (e.g. the lens undistortion) once per read, the last
    ``capacity`` decoded images kept. Thread-safe. uint8 BGR (H, W, 3) like
    :func:`stereoseed.io.files.read_image`."""

    def __init__(self, entries: list[Entry], transform: Transform | None = None, capacity: int = 8,
                 transform_key: bytes = b""):
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self._entries = list(entries)
        self._transform = transform
        self._transform_key = transform_key  # what the transform depends on, for fingerprint()
        self._capacity = capacity
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.reads = 0  # images decoded so far (how well the cache serves the run)

    def __len__(self) -> int:
        return len(self._entries)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            subset = list(range(len(self)))[index]
            transform = self._transform
            return ImageSequence([self._entries[i] for i in subset], None if transform is None else
                                 (lambda j, image: transform(subset[j], image)), self._capacity,
                                 self._transform_key + repr(subset).encode())
        i = range(len(self))[index]  # IndexError and negative indices as a list has them
        with self._lock:
            image = self._cache.get(i)
            if image is not None:
                self._cache.move_to_end(i)
                return image
        entry = self._entries[i]
        image = entry if isinstance(entry, np.ndarray) else read_image(entry)
        if self._transform is not None:
            image = self._transform(i, image)
        if not isinstance(entry, np.ndarray):
            image.flags.writeable = False  # shared by every user of the cache
        with self._lock:
            self.reads += 0 if isinstance(entry, np.ndarray) else 1
            self._cache[i] = image
            self._cache.move_to_end(i)
            while len(self._cache) > self._capacity:
                self._cache.popitem(last=False)
        return image

    def fingerprint(self) -> bytes:
        """A digest of the images the run sees, without decoding them: each file's bytes (an
        image in memory: its pixels) and what the transform depends on."""
        h = hashlib.sha256(self._transform_key)
        for entry in self._entries:
            if isinstance(entry, np.ndarray):
                h.update(str(entry.shape).encode())
                h.update(np.ascontiguousarray(entry).tobytes())
            else:
                h.update(Path(entry).read_bytes())
        return h.digest()

    def source(self, index: int) -> str:
        """Where image ``index`` comes from (its path; "memory" for an array)."""
        entry = self._entries[index]
        return "memory" if isinstance(entry, np.ndarray) else str(entry)
