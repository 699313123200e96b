"""The result folder written as a whole: a staging folder beside it, swapped in at the end."""
from __future__ import annotations

import ctypes
import json
import os
import shutil
import sys
from pathlib import Path

from stereoseed.errors import StereoseedError
from stereoseed.io.files import write_json
from stereoseed.output.results import FORMAT_VERSION

__all__ = ["MANIFEST", "ResultSet"]


MANIFEST = ".stereoseed-result.json"  # written last: lists every file of the result set
_RENAME_EXCHANGE = 2  # <linux/fs.h>


class ResultSet:
    """A result folder written as a whole: the run writes into a staging folder beside it
    (``.NAME.partial``, which also holds the checkpoint for ``--resume``), and :meth:`commit`
    swaps the two folders in one step, so the folder holds either the previous complete result
    set or the new one, never a mix. A folder holding files stereoseed did not write is refused
    before any computation (:meth:`check`): nothing the user made is ever overwritten.

        results = ResultSet(out); results.check()
        staging = results.open()
        ... write every file into staging ...
        results.commit()   # or results.abandon() on failure
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.staging = self.path.parent / f".{self.path.name}.partial"

    def _listed(self) -> set[str] | None:
        """The files the previous result set's manifest lists, None without a manifest."""
        try:
            return set(json.loads((self.path / MANIFEST).read_text())["files"])
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def check(self) -> None:
        """Refuse, before any work: an output path that is a file, a folder holding files
        stereoseed did not write, a place where nothing can be written."""
        if self.path.exists() and not self.path.is_dir():
            raise StereoseedError(f"{self.path}: exists and is not a folder; give a folder for the results")
        if self.path.is_dir():
            present = {str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.is_file()}
            foreign = sorted(present - (self._listed() or set()) - {MANIFEST})
            if foreign:
                more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
                raise StereoseedError(f"{self.path}: holds files stereoseed did not write ({', '.join(foreign[:3])}"
                                      f"{more}); give an empty or new folder for the results")
        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            probe = parent / f".{self.path.name}.probe"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as e:
            raise StereoseedError(f"{self.path}: cannot write there ({e.strerror or e}); give a writable folder") from None

    def open(self, keep: bool = False) -> Path:
        """The staging folder, emptied unless ``keep`` (a resumed run keeps its checkpoint)."""
        if self.staging.exists() and not keep:
            shutil.rmtree(self.staging)
        self.staging.mkdir(parents=True, exist_ok=True)
        return self.staging

    def commit(self, drop: tuple[str, ...] = ()) -> Path:
        """Make the staging folder the result folder (files and folders named in ``drop``,
        e.g. the checkpoint, are removed first); the previous result set is deleted."""
        for name in drop:
            path = self.staging / name
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        files = sorted(str(p.relative_to(self.staging)) for p in self.staging.rglob("*") if p.is_file())
        write_json(self.staging / MANIFEST, {"format_version": FORMAT_VERSION, "files": files})
        if self.path.exists() and _exchange(self.staging, self.path):
            shutil.rmtree(self.staging)  # the previous result set, swapped out
        else:
            old = self.path.parent / f".{self.path.name}.old"
            if self.path.exists():
                shutil.rmtree(old, ignore_errors=True)
                os.replace(self.path, old)
            os.replace(self.staging, self.path)
            shutil.rmtree(old, ignore_errors=True)
        return self.path

    def abandon(self) -> None:
        """Forget the staging folder (the result folder is untouched)."""
        shutil.rmtree(self.staging, ignore_errors=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders atomically (Linux renameat2 RENAME_EXCHANGE); False where unavailable."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0
