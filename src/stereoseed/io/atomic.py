"""Atomic writing: a file is written under a temporary name in its folder, then renamed over
its name, so an interrupted run never leaves a half-written file. Re-exported by
:mod:`stereoseed.io.files`."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.errors import StereoseedError

__all__ = ["atomic_path", "jsonable", "write_json", "write_text"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


UMASK_AT_IMPORT = _umask()  # read once, before any thread of ours writes (setting it to read it races them)
_FILE_MODE = 0o666 & ~UMASK_AT_IMPORT  # what open() would give: mkstemp's files are 0600


NAME_MAX = 255  # bytes of one file name (Linux's and macOS's file systems): the temporary name must fit too
_RANDOM = 8  # the characters mkstemp puts between the prefix and the suffix


def _temporary_prefix(name: str, suffix: str) -> str:
    """``.NAME.``, NAME cut (at a character) so that the temporary name fits in NAME_MAX bytes:
    an image name of 250 bytes is a name the file system takes, its temporary one must be too."""
    room = NAME_MAX - len(os.fsencode(suffix)) - _RANDOM - 2
    cut = os.fsencode(name)[:max(room, 0)]
    return "." + cut.decode("utf-8", "ignore") + "."


class atomic_path:
    """Context manager yielding a temporary path that replaces ``path`` on success (created with
    the user's umask); on failure the temporary file is removed. Errors name ``path``, never the
    temporary file."""

    def __init__(self, path: str | os.PathLike, suffix: str = ""):
        self.path = Path(path)
        self.suffix = suffix or self.path.suffix

    def __enter__(self) -> Path:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(self.path.name, ".tmp" + self.suffix),
                                       suffix=".tmp" + self.suffix, dir=self.path.parent)
        except OSError as e:
            raise StereoseedError(f"{self.path}: cannot write ({e.strerror or e})") from None
        os.close(fd)
        self.tmp = Path(tmp)
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                os.chmod(self.tmp, _FILE_MODE)
                os.replace(self.tmp, self.path)
                return False
            except OSError as e:
                self.tmp.unlink(missing_ok=True)
                raise StereoseedError(f"{self.path}: cannot write ({e.strerror or e})") from None
        self.tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise StereoseedError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        return False


def jsonable(obj: Any) -> Any:
    """``json.dumps``'s ``default``: NumPy arrays become lists, NumPy scalars Python numbers,
    paths strings."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically; NumPy arrays become lists."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=jsonable) + "\n", encoding="utf-8")
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` as UTF-8 (whatever the locale: image names may not be ASCII), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
