"""The result folder written as a whole: a staging folder beside it, swapped in at the end, one
run at a time."""
from __future__ import annotations

import ctypes
import fnmatch
import json
import logging
import os
import re
import shutil
import stat
import sys
import tempfile
from pathlib import Path

from stereoseed.io.atomic import UMASK_AT_IMPORT
from stereoseed.errors import StereoseedError
from stereoseed.io.files import write_json
from stereoseed.output.results import FORMAT_VERSION

try:  # POSIX; elsewhere runs on one folder are not kept apart
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["MANIFEST", "STAGING_MARKER", "ResultSet", "result_name", "staging_folder"]

log = logging.getLogger(__name__)

MANIFEST = ".stereoseed-result.json"  # written last: lists every file of the result set
STAGING_MARKER = ".stereoseed-staging"  # written first into a staging folder: what says it is stereoseed's
_RENAME_EXCHANGE = 2  # <linux/fs.h>
_LOCK_TEXT = re.compile(rb"stereoseed (\d+)\n?")


class ResultSet:
    """A result folder written as a whole: the run writes into a staging folder beside it
    (``.NAME.partial``, which also holds the checkpoint for ``--resume``), and :meth:`commit`
    swaps the two folders in one step, so the folder holds either the previous complete result
    set or the new one, never a mix. A folder holding files stereoseed did not write is refused
    before any computation (:meth:`check`), and so is a ``.NAME.partial`` that stereoseed did not
    make (its marker file is missing): nothing the user made is ever overwritten or removed.
    A run holds the lock ``.NAME.lock`` beside the folder while it works (the ``with`` block):
    a second run on the same folder is refused at once, touching nothing.

        with ResultSet(out) as results:
            results.check()
            staging = results.open()
            ... write every file into staging ...
            results.commit()   # or results.abandon() on failure

    ``out`` may be a symbolic link to a folder: the folder it points to is written, the link
    stays as it is.
    """

    def __init__(self, path: str | Path):
        self.shown = Path(path)  # as the user wrote it, for messages
        # the real folder: a link's target is what is written (a link renamed away or replaced by
        # a folder would break every later run), and one folder has one lock however it is named
        self.path = Path(os.path.realpath(path))
        if not self.path.name:
            raise StereoseedError(f"{self.shown}: is the root folder; give a folder for the results")
        self.staging = staging_folder(self.path)
        self.lock_path = self.path.parent / f".{self.path.name}.lock"
        self._lock_fd: int | None = None

    # ------------------------------------------------------------------ one run at a time
    def lock(self) -> "ResultSet":
        """Take the exclusive lock of this result folder (a ``flock`` on ``.NAME.lock``, kept
        until :meth:`unlock`); another run holding it is refused with one line."""
        if fcntl is None or self._lock_fd is not None:
            return self
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise StereoseedError(f"{self.shown}: cannot write there ({e.strerror or e}); give a writable folder") from None
        while True:
            fd = self._open_lock_file()
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _lock_owner(fd)
                os.close(fd)
                raise StereoseedError(f"another stereoseed run is writing {self.shown} (pid {pid}); wait for it or "
                                      f"choose another --out") from None
            except OSError as e:  # a file system without locks
                os.close(fd)
                raise StereoseedError(f"{self.lock_path}: cannot be locked ({e.strerror or e}); give a folder on a "
                                      f"local disk for the results") from None
            # the run that held it may have removed the file between our open and our lock: the
            # lock must be on the file that bears the name
            try:
                named = os.lstat(self.lock_path)
            except FileNotFoundError:
                os.close(fd)
                continue
            held = os.fstat(fd)
            if (named.st_dev, named.st_ino) != (held.st_dev, held.st_ino):
                os.close(fd)
                continue
            break
        text = os.pread(fd, 64, 0)
        if text and not _LOCK_TEXT.fullmatch(text):
            os.close(fd)
            raise StereoseedError(f"{self.lock_path}: exists and is not a stereoseed lock; move it away or choose "
                                  f"another --out")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"stereoseed {os.getpid()}\n".encode(), 0)
        self._lock_fd = fd
        return self

    def _open_lock_file(self) -> int:
        flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(self.lock_path, flags, 0o600)
        except OSError as e:
            if os.path.islink(self.lock_path):
                raise StereoseedError(f"{self.lock_path}: is a symbolic link, not stereoseed's lock; move it away or "
                                      f"choose another --out") from None
            raise StereoseedError(f"{self.shown}: cannot write there ({e.strerror or e}); give a writable folder") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise StereoseedError(f"{self.lock_path}: is not a file; move it away or choose another --out")
        return fd

    def unlock(self) -> None:
        """Let the next run in: the lock file is removed while still held (a run waiting on the
        old file sees it is gone and takes a new one)."""
        fd, self._lock_fd = self._lock_fd, None
        if fd is None:
            return
        try:
            named, held = os.lstat(self.lock_path), os.fstat(fd)
            if (named.st_dev, named.st_ino) == (held.st_dev, held.st_ino):
                os.unlink(self.lock_path)
        except OSError:
            pass
        finally:
            os.close(fd)

    def __enter__(self) -> "ResultSet":
        return self.lock()

    def __exit__(self, *exc: object) -> None:
        self.unlock()

    # ------------------------------------------------------------------ the folders
    def _listed(self) -> set[str] | None:
        """The files the previous result set's manifest lists, None without a manifest."""
        return read_manifest(self.path / MANIFEST)

    def check(self) -> None:
        """Refuse, before any work: an output path that is a file, a folder holding files
        stereoseed did not write, a place where nothing can be written."""
        if os.path.islink(self.path):  # realpath stopped at it: a loop of links (a dangling one resolves)
            raise StereoseedError(f"{self.shown}: is a symbolic link that leads to no folder (a loop of links); "
                                  f"remove it or give a folder for the results")
        if self.path.exists() and not self.path.is_dir():
            raise StereoseedError(f"{self.shown}: exists and is not a folder; give a folder for the results")
        if os.path.ismount(self.path):  # the results are renamed into place: a mount point cannot be
            raise StereoseedError(f"{self.shown}: is a mount point (a volume); the results are swapped in by "
                                  f"renaming, which a mount point refuses: give a folder inside it, e.g. "
                                  f"{self.shown / 'results'}")
        if self.path.is_dir():
            foreign = _foreign(self.path, (self._listed() or set()) | {MANIFEST})
            if foreign:
                more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
                raise StereoseedError(f"{self.shown}: holds files stereoseed did not write ({', '.join(foreign[:3])}"
                                      f"{more}); give an empty or new folder for the results")
        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            # a name of its own: a user's file beside the results is never touched
            fd, probe = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".probe", dir=parent)
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise StereoseedError(f"{self.shown}: cannot write there ({e.strerror or e}); give a writable folder") from None

    def _ours(self) -> bool:
        """Whether the staging folder is a folder stereoseed made (its marker is a plain file)."""
        try:
            return stat.S_ISREG(os.lstat(self.staging / STAGING_MARKER).st_mode)
        except OSError:
            return False

    def open(self, keep: tuple[str, ...] = ()) -> Path:
        """The staging folder (readable and writable by the user alone: it holds the checkpoint),
        emptied of everything but the names in ``keep`` (a resumed run keeps its checkpoint).
        A ``.NAME.partial`` that stereoseed did not make is refused, never emptied."""
        try:
            st = os.lstat(self.staging)
        except FileNotFoundError:
            st = None
        except OSError as e:
            raise StereoseedError(f"{self.staging}: cannot be read ({e.strerror or e}); move it away or choose "
                                  f"another --out") from None
        if st is not None and not stat.S_ISDIR(st.st_mode):
            raise StereoseedError(f"{self.staging}: exists and is not stereoseed's staging folder; move it away or "
                                  f"choose another --out")
        if st is not None and not self._ours():
            try:
                self.staging.rmdir()  # empty: a run stopped between making it and marking it
            except OSError:
                raise StereoseedError(f"{self.staging}: a folder stereoseed did not make (no {STAGING_MARKER} in it) "
                                      f"is where the results are staged; move it away or choose another "
                                      f"--out") from None
            st = None
        try:
            if st is None:
                self.staging.mkdir(mode=0o700)
                write_json(self.staging / STAGING_MARKER, {"stereoseed": "staging folder", "result": str(self.path)})
            else:
                for entry in self.staging.iterdir():
                    if entry.name != STAGING_MARKER and (entry.name not in keep or not _plain(entry)):
                        if entry.name in keep:  # reading a FIFO planted as the checkpoint would wait forever
                            log.warning("%s: not a file or folder stereoseed writes; removed", entry)
                        _remove(entry)
        except OSError as e:
            raise StereoseedError(f"{self.staging}: cannot write ({e.strerror or e}); give a writable folder") from None
        return self.staging

    def commit(self, drop: tuple[str, ...] = ()) -> Path:
        """Make the staging folder the result folder; the entries whose names match a pattern
        of ``drop`` (e.g. ``.checkpoint*``: the checkpoint, its spill folder, a stale one of
        another name) are removed first; the previous result set is deleted."""
        for entry in list(self.staging.iterdir()):
            if entry.name == STAGING_MARKER or any(fnmatch.fnmatchcase(entry.name, p) for p in drop):
                _remove(entry)
        files = sorted(str(p.relative_to(self.staging)) for p in self.staging.rglob("*") if p.is_file())
        write_json(self.staging / MANIFEST, {"format_version": FORMAT_VERSION, "files": files})
        os.chmod(self.staging, 0o777 & ~_read_umask())  # a folder of the user's, as mkdir makes it
        if self.path.exists() and _exchange(self.staging, self.path):
            shutil.rmtree(self.staging)  # the previous result set, swapped out
            return self.path
        old = None
        try:
            if self.path.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".old", dir=self.path.parent))
                os.replace(self.path, old)  # onto the empty folder just made: a name nobody else uses
            os.replace(self.staging, self.path)
        except OSError as e:  # the swap refused (a mount point made since check(), a busy folder)
            self._undo_swap(old)
            raise StereoseedError(f"{self.shown}: the results could not be moved into place ({e.strerror or e}); "
                                  f"they stay in {self.staging} (the previous results are untouched); give "
                                  f"another --out") from None
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return self.path

    def _undo_swap(self, old: Path | None) -> None:
        """After a failed swap: the previous result set back under its name, the empty ``.old``
        folder gone, the staging folder marked as stereoseed's again (the next run empties it;
        unmarked it would be refused as the user's)."""
        try:
            if old is not None:
                if not self.path.exists() and any(old.iterdir()):
                    os.replace(old, self.path)
                else:
                    old.rmdir()
            if self.staging.is_dir():
                write_json(self.staging / STAGING_MARKER, {"stereoseed": "staging folder", "result": str(self.path)})
        except (OSError, StereoseedError):
            log.warning("%s: could not be put back as it was after the failed swap", self.shown, exc_info=True)

    def abandon(self) -> None:
        """Forget the staging folder (the result folder is untouched); only a folder that
        stereoseed made is removed."""
        if self._ours():
            shutil.rmtree(self.staging, ignore_errors=True)


def _plain(entry: Path) -> bool:
    """Whether ``entry`` is a regular file or a real folder (not a link, a FIFO, a socket, a device)."""
    try:
        mode = os.lstat(entry).st_mode
    except OSError:
        return False
    return stat.S_ISREG(mode) or stat.S_ISDIR(mode)


def staging_folder(path: Path) -> Path:
    """Where the result set of ``path`` is written before it is swapped in: ``.NAME.partial`` beside it."""
    return path.parent / f".{path.name}.partial"


def result_name(folder: str | Path) -> str:
    """The result folder's name: ``folder``'s, or for a staging folder (:func:`staging_folder`,
    holding stereoseed's marker) the NAME it becomes."""
    folder = Path(folder).resolve()
    name = folder.name
    if name.startswith(".") and name.endswith(".partial") and len(name) > len("..partial") \
            and (folder / STAGING_MARKER).is_file():
        return name[1:-len(".partial")]
    return name


def read_manifest(path: Path) -> set[str] | None:
    """The files a manifest (ours: a result set's, an export's) lists; None when there is none
    or it is not one."""
    try:
        files = json.loads(path.read_text(encoding="utf-8"))["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return {f for f in files if isinstance(f, str)} if isinstance(files, list) else None


def add_to_manifest(folder: Path, relative: str) -> bool:
    """List the file ``relative`` in ``folder``'s result-set manifest (when the folder has one: a
    staging folder gets its manifest when it is committed), its other keys kept. False when the
    manifest cannot be read (the file is then not listed). The caller holds the folder's lock."""
    manifest = folder / MANIFEST
    if not manifest.is_file():
        return True
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
        files = data["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if isinstance(files, list) and relative not in files:
        data["files"] = sorted([*files, relative])
        write_json(manifest, data)
    return True


def _remove(path: Path) -> None:
    """A file, a link or a whole folder (a link to a folder is removed, not followed)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def _foreign(root: Path, listed: set[str]) -> list[str]:
    """What ``root`` holds that is not in ``listed`` (paths relative to it; a folder that holds
    no listed file is named once, with a trailing '/', not walked)."""
    holding = {str(p) for f in listed for p in Path(f).parents}
    foreign = []
    for folder, dirs, files in os.walk(root):  # links to folders are listed, not followed
        rel = Path(folder).relative_to(root)
        for d in sorted(dirs):
            if str(rel / d) not in holding:
                foreign.append(f"{rel / d}/")
        dirs[:] = sorted(d for d in dirs if str(rel / d) in holding)
        foreign += sorted(str(rel / f) for f in files if str(rel / f) not in listed)
    return foreign


def _read_umask() -> int:
    """The process's umask without changing it, where the system says it (Linux); otherwise
    as it was when this module was imported (setting it to read it would race other threads'
    files)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return UMASK_AT_IMPORT


def _lock_owner(fd: int) -> str:
    """The pid written in a lock file, '?' when it cannot be read."""
    try:
        m = _LOCK_TEXT.fullmatch(os.pread(fd, 64, 0))
    except OSError:
        m = None
    return m.group(1).decode() if m else "?"


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
