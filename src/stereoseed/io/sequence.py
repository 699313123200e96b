"""The ordered input images of a run, read when needed rather than all at once.

A walk filmed or photographed around an object has hundreds of images; the mapper works on the
last few (and the loop closure on the first few), so holding every decoded image would make the
memory grow with the sequence. :class:`ImageSequence` decodes an image when it is asked for and
keeps the most recently used ones (a small LRU, shared by the mapper and the thread that
prefetches interest points). It is a ``Sequence``: ``reconstruct`` takes it or a plain list.

Two kinds of image of the walk are not decoded into the run, so that the mapper skips them with
their reason instead of the run stopping: one whose header gives another size than the camera's
(:meth:`ImageSequence.withhold_other_sizes`) and one that cannot be decoded at all
(:meth:`ImageSequence.skip_unreadable`).
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from typing import Callable, Union

import numpy as np

from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_image
from stereoseed.io.image_header import header_size  # re-exported: the walk's and the hand-offs' home of it

__all__ = ["ImageSequence", "header_size"]

_FINGERPRINT_CHUNK = 2**20  # bytes of a file hashed at a time (the same digest as the whole file's)

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
        self._expected: tuple[int, int] | None = None  # (width, height) of the images from _checked_from on
        self._checked_from = len(self._entries)
        self._headers: dict[int, tuple[int, int] | None] = {}  # index -> the size its file's header gives, read once
        self._skip_from = len(self._entries)  # images from here on that cannot be decoded are skipped
        self._unreadable: dict[int, str] = {}  # index -> why it cannot be decoded
        self._fingerprint: tuple[int, bytes] | None = None  # (images digested, their digest)

    def withhold_other_sizes(self, size: tuple[int, int], first: int = 0) -> None:
        """From image ``first`` on, an image file whose header gives another size than ``size``
        (width, height; either way round, as a photo's orientation tag may turn it) is not
        decoded: it reads as a black image of its size that takes no memory (a zero-stride
        array), for a consumer that refuses it by its size alone. Formats whose header is not
        read here (:func:`header_size`) are decoded as usual."""
        self._expected = (int(size[0]), int(size[1]))
        self._checked_from = first

    def skip_unreadable(self, first: int = 0) -> None:
        """From image ``first`` on, an image file that cannot be decoded (damaged, truncated, not
        an image) does not raise: its reason is kept (:meth:`unreadable`) and it reads as a
        black image that takes no memory, for a consumer that asks :meth:`unreadable` before
        working on it. Its size is its header's; when the header says nothing, the size the
        images are expected to have (:meth:`withhold_other_sizes`), else 0 x 0: the result
        lists every input image with a size."""
        self._skip_from = first

    def unreadable(self, index: int) -> str | None:
        """Why image ``index`` cannot be decoded (the reader's message), None when it can or when
        :meth:`skip_unreadable` does not cover it (it then raises as it is read). The image is
        read to know, and then kept in the cache like any other."""
        i = range(len(self))[index]
        if i < self._skip_from or isinstance(self._entries[i], np.ndarray) or self._withheld_size(i) is not None:
            return None
        with self._lock:
            if i in self._unreadable or i in self._cache:
                return self._unreadable.get(i)
        self[i]
        return self._unreadable.get(i)

    def withheld(self, index: int) -> bool:
        """Whether image ``index`` is not decoded (:meth:`withhold_other_sizes`)."""
        return self._withheld_size(range(len(self))[index]) is not None

    def _withheld_size(self, i: int) -> tuple[int, int] | None:
        if self._expected is None or i < self._checked_from or isinstance(self._entries[i], np.ndarray):
            return None
        size = self._header(i)
        return None if size is None or self._expected in (size, size[::-1]) else size

    def _unreadable_size(self, i: int) -> tuple[int, int]:
        return self._header(i) or self._expected or (0, 0)

    def _header(self, i: int) -> tuple[int, int] | None:
        if i not in self._headers:
            self._headers[i] = header_size(self._entries[i])
        return self._headers[i]

    def __len__(self) -> int:
        return len(self._entries)

    def append(self, entry: Entry) -> int:
        """One more image at the end (a live run learns its images one at a time); it is
        checked and skipped as the others from their ``first`` on. Returns its index."""
        with self._lock:
            self._entries.append(entry)
            return len(self._entries) - 1

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            subset = list(range(len(self)))[index]
            transform = self._transform
            part = ImageSequence([self._entries[i] for i in subset], None if transform is None else
                                 (lambda j, image: transform(subset[j], image)), self._capacity,
                                 self._transform_key + repr(subset).encode())
            if self._expected is not None:  # the images checked here stay checked there
                part.withhold_other_sizes(self._expected, next((j for j, i in enumerate(subset)
                                                                if i >= self._checked_from), len(subset)))
            part.skip_unreadable(next((j for j, i in enumerate(subset) if i >= self._skip_from), len(subset)))
            return part
        i = range(len(self))[index]  # IndexError and negative indices as a list has them
        size = self._withheld_size(i)
        if size is not None:
            return _blank(size)
        with self._lock:
            if i in self._unreadable:  # decoded once: the same answer for the rest of the run
                return _blank(self._unreadable_size(i))
            image = self._cache.get(i)
            if image is not None:
                self._cache.move_to_end(i)
                return image
        entry = self._entries[i]
        try:
            image = entry if isinstance(entry, np.ndarray) else read_image(entry)
        except StereoseedError as e:
            if i < self._skip_from:
                raise
            with self._lock:
                self._unreadable[i] = str(e)
            return _blank(self._unreadable_size(i))
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
        image in memory: its pixels) and what the transform depends on. Kept until an image is
        appended: a live run's stop signs its checkpoint and resumes from it, two digests of the
        same photos."""
        if self._fingerprint is not None and self._fingerprint[0] == len(self._entries):
            return self._fingerprint[1]
        h = hashlib.sha256(self._transform_key)
        for entry in self._entries:
            if isinstance(entry, np.ndarray):
                h.update(str(entry.shape).encode())
                h.update(np.ascontiguousarray(entry).tobytes())
            else:  # a chunk at a time: a 3 GB file the walk skips by its header is not held whole
                with open(entry, "rb") as f:
                    while chunk := f.read(_FINGERPRINT_CHUNK):
                        h.update(chunk)
        self._fingerprint = (len(self._entries), h.digest())
        return self._fingerprint[1]

    def source(self, index: int) -> str:
        """Where image ``index`` comes from (its path; "memory" for an array)."""
        entry = self._entries[index]
        return "memory" if isinstance(entry, np.ndarray) else str(entry)


def _blank(size: tuple[int, int]) -> np.ndarray:
    """A black image of ``size`` (width, height) that takes no memory (a zero-stride view)."""
    return np.broadcast_to(np.zeros((1, 1, 3), np.uint8), (size[1], size[0], 3))
