"""The rule every writer (``target``, ``calibrate``, ``intrinsics``, ``match``, ``propagate``,
``export``, ``mesh``) follows before it writes: an output, given or derived from another name
(``<stem>_target.json``, a check image), is never one of the command's inputs; and an existing
file is replaced or removed only when stereoseed wrote it, byte for byte: a file of the same name
the user wrote, or edited since, is refused even with ``--force``.

How a file is known to be stereoseed's: a record in its folder of the files written there, each
with its SHA-256 (:class:`OwnedFiles`): ``target``'s own record of its folder, and for the
single files (``calibrate -o`` and its ``<stem>_target.json`` and check images, ``intrinsics -o``,
``match -o``, ``propagate -o``) the record ``WRITTEN_RECORD`` beside them
(:func:`refuse_foreign_file` before the work, :func:`record_written_file` after each write). A
hash, not a marker in the file: a user's file cannot carry it by accident (a copy of an earlier
output edited by hand no longer matches), and it works for every format (PNG, JPEG, YAML, XML).
``export`` and ``mesh`` keep their own marks (the export's manifest, the mesh's PLY header).

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

__all__ = ["same_file", "refuse_input_as_output", "OwnedFiles", "WRITTEN_RECORD", "refuse_foreign_file",
           "record_written_file"]

_HASH_CHUNK = 2**20  # files are hashed a chunk at a time: a page PDF is megabytes, none is held whole
# beside the single files the commands write (calib.json, camera.yaml, check and match images): which
# of the folder's files stereoseed wrote, with their hashes; hidden, as it is no output to open
WRITTEN_RECORD = ".stereoseed-written.json"


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

    def wrote_file(self, name: str) -> None:
        """Note that the command wrote the folder's file ``name`` as it is now (saved by :meth:`save`)."""
        digest = _sha256(self.folder / name)
        if digest is None:  # not written after all (nothing there, or a link): nothing to claim
            self.forget(name)
        else:
            self._hashes[name] = digest

    def wrote(self, name: str, data: bytes) -> None:
        """Note that the command wrote ``data`` as ``name`` (saved by :meth:`save`)."""
        self._hashes[name] = hashlib.sha256(data).hexdigest()

    def forget(self, name: str) -> None:
        self._hashes.pop(name, None)

    def save(self) -> None:
        write_json(self.record, {"written_by": self.command, "files": dict(sorted(self._hashes.items()))})


def _single_files(folder: Path) -> OwnedFiles:
    return OwnedFiles(folder, WRITTEN_RECORD, "stereoseed")


def refuse_foreign_file(output: str | os.PathLike, hint: str) -> None:
    """The writers' rule for one output file, before any work: refuse ``output`` when a file (or
    a folder, a link) is there that stereoseed did not write, or that changed since; one it wrote
    is the command's to replace. ``hint`` says what to give instead (e.g. "give another -o").
    Also refused: a record of that name that is no record (:class:`OwnedFiles`), and the record's
    own name as an output."""
    path = Path(output)
    if path.name == WRITTEN_RECORD:
        raise StereoseedError(f"{path}: is the name of stereoseed's record of the files it wrote; {hint}")
    owned = _single_files(path.parent)  # read even for a new file: a record that is none is refused now, not after the work
    if (path.exists() or path.is_symlink()) and not owned.ours(path.name):
        raise StereoseedError(f"{path}: exists and stereoseed did not write it (or it changed since); it is left as "
                              f"it is: {hint}, or remove it yourself")


def record_written_file(output: str | os.PathLike) -> None:
    """Note in the record beside ``output`` that stereoseed wrote it as it is now. The record is
    read again here, not kept from the check before the work (minutes earlier): another command
    may have written into the folder meanwhile. Two writing at the same instant may lose one
    entry; that file is then refused on a later run, never replaced."""
    path = Path(output)
    owned = _single_files(path.parent)
    owned.wrote_file(path.name)
    owned.save()
