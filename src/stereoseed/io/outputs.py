"""The rule every writer (``target``, ``calibrate``, ``intrinsics``, ``match``, ``propagate``,
``export``, ``mesh``) follows before it writes: an output, given or derived from another name
(``<stem>_target.json``, a check image), is never one of the command's inputs; and in a folder a
command shares with the user, a file is replaced or removed only when the command's own record
says it wrote it, byte for byte (:class:`OwnedFiles`): a file of the same name the user wrote,
or edited since, is refused even with ``--force``.

Both refusals come before any work, in one line naming the file and what to do.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Iterable

from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import write_json
from stereoseed.io.nesting import read_bounded_text

__all__ = ["same_file", "refuse_input_as_output", "OwnedFiles"]

_HASH_CHUNK = 2**20  # files are hashed a chunk at a time: a page PDF is megabytes, none is held whole


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether writing ``a`` would write ``b``: the same file (a hard link, a symlink to it, another
    spelling of its path), or, when either does not exist yet, the same resolved path."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        pass
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):  # a symlink loop: nothing to compare, and nothing written there either
        return False


def refuse_input_as_output(output: str | os.PathLike, inputs: Iterable[str | os.PathLike | None], hint: str) -> None:
    """Raise :class:`StereoseedError` when ``output`` is one of ``inputs`` (None entries: an
    option not given); ``hint`` says what to give instead (e.g. "give another -o")."""
    for given in inputs:
        if given is not None and same_file(output, given):
            same = "" if str(given) == str(output) else f" ({given})"
            raise StereoseedError(f"{output}: is also an input{same}; writing it would destroy it; {hint}")


def _sha256(path: Path) -> str | None:
    """A regular file's SHA-256 (hex); None for anything else (a link, a folder, a FIFO: never ours)."""
    if path.is_symlink() or not path.is_file():
        return None
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while chunk := f.read(_HASH_CHUNK):
                digest.update(chunk)
    except OSError:
        return None
    return digest.hexdigest()


class OwnedFiles:
    """A folder's record (the JSON file ``record_name`` in it) of the files a command wrote there,
    each with its SHA-256: what the command may replace or remove on a later run. A record that is
    not one (the user's file of that name, unreadable) is refused, so that it is not overwritten."""

    def __init__(self, folder: str | os.PathLike, record_name: str, command: str):
        self.folder, self.record, self.command = Path(folder), Path(folder) / record_name, command
        self._hashes: dict[str, str] = {}
        if self.record.exists() or self.record.is_symlink():
            try:
                files = json.loads(read_bounded_text(self.record, "record", ""))["files"]
                if not isinstance(files, dict):
                    raise TypeError
                self._hashes = {k: v for k, v in files.items() if isinstance(k, str) and isinstance(v, str)}
            except (OSError, ValueError, KeyError, TypeError, StereoseedError):
                raise StereoseedError(f"{self.record}: is not the record {command} keeps of the files it wrote; "
                                      f"move it away or give another folder") from None

    def ours(self, name: str) -> bool:
        """Whether the file ``name`` in the folder is what the command wrote there, unchanged."""
        recorded = self._hashes.get(name)
        return recorded is not None and _sha256(self.folder / name) == recorded

    def refuse_foreign(self, names: Iterable[str]) -> None:
        """Raise :class:`StereoseedError` for the first of ``names`` that exists in the folder and
        is not the command's (a file the user put there, or one changed since it was written)."""
        for name in names:
            path = self.folder / name
            if (path.exists() or path.is_symlink()) and not self.ours(name):
                raise StereoseedError(f"{path}: {self.command} did not write it (or it changed since); it is left "
                                      f"as it is: move it away or give another folder")

    def wrote(self, name: str, data: bytes) -> None:
        """Note that the command wrote ``data`` as ``name`` (saved by :meth:`save`)."""
        self._hashes[name] = hashlib.sha256(data).hexdigest()

    def forget(self, name: str) -> None:
        self._hashes.pop(name, None)

    def save(self) -> None:
        write_json(self.record, {"written_by": self.command, "files": dict(sorted(self._hashes.items()))})
