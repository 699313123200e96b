"""The sample sets (Middlebury, Strecha, ChArUco photos) for a clone without ../shared:
:func:`fetch` downloads one into the user's data folder in the layout ../shared/data holds (the
layout the tests and benchmarks read), :func:`sample_status` says which are present where.
``stereoseed data fetch NAME`` and ``stereoseed data list`` are thin over these.

Nothing is kept unless its checksum was checked (:mod:`stereoseed.io.sample_registry`), and
nothing looks complete before it is: downloads go to a hidden folder beside the sets (pooch
writes each under a temporary name and renames it once its SHA-256 matches), the set is
unpacked and converted in a hidden staging folder, and renamed to its name last, with a
marker file naming what it holds. A folder of that name that stereoseed did not write is never
touched. ``$STEREOSEED_DATA``, else ../shared/data beside the checkout, is an offline mirror: a
set found there is not downloaded.
"""
from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import shutil
import stat
import tempfile
import zipfile
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import Iterator, NamedTuple

from stereoseed.errors import StereoseedError
from stereoseed.io.sample_convert import convert_strecha
from stereoseed.io.sample_registry import SETS, Download, SampleSet

__all__ = ["fetch", "find_sample", "missing_message", "sample_status", "default_data_dir", "offline_mirror", "SETS"]

log = logging.getLogger(__name__)

# requests' timeout: seconds without a byte from the server (connecting or reading), not the
# whole download's: a slow line still finishes, a dead one is reported within a minute
DOWNLOAD_TIMEOUT_S = 60
# Bounds on an archive, checked on its directory before a byte is unpacked (a zip bomb declares
# little and unpacks to gigabytes). The largest file of any set is a 3072x2048 JPEG of about
# 3 MB and the largest zip (a Middlebury ring) unpacks to about 4 MB: these leave a wide margin.
MAX_MEMBER_BYTES = 64 * 2**20
MAX_ARCHIVE_BYTES = 256 * 2**20
MAX_MEMBERS = 4096
# photographs barely compress and text about 10x; a bomb's members compress 1000x or more
MAX_COMPRESSION_RATIO = 100
CHUNK_BYTES = 2**20  # unpacking and hashing read this much at a time: memory stays flat

MARKER = ".stereoseed-fetch.json"  # written last into a set's folder: stereoseed wrote it, complete
DOWNLOADS = ".stereoseed-downloads"  # beside the sets: files downloaded, kept until their set is in place
PARTIAL = ".partial-"  # staging folders: ".NAME.partial-XXXX" beside the sets


class SetStatus(NamedTuple):
    name: str
    about: str
    where: Path | None  # the folder holding it (the mirror's or the data folder's), None: absent
    fetchable: bool  # every download has a checksum to check it against
    cite: str


def default_data_dir() -> Path:
    """Where fetched sets go without ``--dir``: the user's data folder
    (``$XDG_DATA_HOME/stereoseed``, by default ``~/.local/share/stereoseed`` on Linux)."""
    import platformdirs

    return Path(platformdirs.user_data_dir("stereoseed", appauthor=False))


def offline_mirror() -> Path:
    """The folder of sets already on this machine: $STEREOSEED_DATA, else ``shared/data`` beside
    the checkout (src/stereoseed/io/ -> the folder holding the repository)."""
    env = os.environ.get("STEREOSEED_DATA")
    if env:
        return Path(env).expanduser().resolve()
    return Path(__file__).resolve().parents[4] / "shared" / "data"


def _sample_set(name: str) -> SampleSet:
    if name not in SETS:
        raise StereoseedError(f"{name!r}: no such sample set; the sets are {', '.join(SETS)} "
                              "(stereoseed data list)")
    return SETS[name]


def _complete(folder: Path) -> bool:
    return (folder / MARKER).is_file()


def find_sample(name: str, data_dir: str | os.PathLike | None = None) -> Path | None:
    """The folder holding set ``name``: the offline mirror's, else the data folder's (a complete
    fetch), else None."""
    mirrored = offline_mirror() / name
    if mirrored.is_dir():
        return mirrored
    fetched = Path(data_dir) if data_dir else default_data_dir()
    return fetched / name if _complete(fetched / name) else None


def missing_message(name: str) -> str:
    """Why set ``name`` is not here and how to get it (a test's skip reason, a benchmark's note)."""
    where = f"{name} not found in the offline mirror {offline_mirror()} ($STEREOSEED_DATA)"
    if name not in SETS:  # a set of ../shared/data that data fetch does not know (dinoRing1-24)
        return f"{where}; put it there (data fetch has no source for it)"
    if _unverifiable(SETS[name]):
        return f"{where}; put it there (data fetch has no checksums recorded for it yet)"
    return f"{where} nor in {default_data_dir()}; run: stereoseed data fetch {name}"


def _unverifiable(sset: SampleSet) -> list[Download]:
    """The downloads no checksum here checks: a file without its SHA-256, a zip without its
    own nor a manifest to check its members against."""
    return [d for d in sset.downloads if d.sha256 is None and not (d.kind == "zip" and sset.manifest)]


def sample_status(data_dir: str | os.PathLike | None = None) -> list[SetStatus]:
    """Every set, where it is (:func:`find_sample`) and whether it can be fetched."""
    return [SetStatus(s.name, s.about, find_sample(s.name, data_dir), not _unverifiable(s), s.cite)
            for s in SETS.values()]


def fetch(name: str, data_dir: str | os.PathLike | None = None, progress: bool = False) -> Path:
    """Set ``name`` in the layout ../shared/data holds; returns its folder.

    Without ``data_dir``: the offline mirror's folder when it holds the set (nothing is
    downloaded), else ``default_data_dir() / name``, downloaded when not already there. With
    ``data_dir``: ``data_dir / name``, copied from the mirror when it holds the set, else
    downloaded. ``progress``: pooch's progress bar on stderr (for the command line).

    Refused (:class:`StereoseedError`, nothing left behind): an unknown name, a set with a
    download no checksum checks, an unreachable server, a file whose checksum differs, an
    archive with a member outside its folder, a link or a size past the bounds above, a full
    disk, a folder of that name that stereoseed did not write."""
    sset = _sample_set(name)
    root = Path(data_dir).expanduser() if data_dir else default_data_dir()
    target = root / name
    if _complete(target):
        log.info("%s: already fetched in %s", name, target)
        return target
    mirrored = offline_mirror() / name
    if mirrored.is_dir() and (data_dir is None or mirrored.resolve() == target.resolve()):
        log.info("%s: in the offline mirror %s, nothing downloaded", name, mirrored)
        return mirrored
    if target.exists():
        raise StereoseedError(f"{target}: exists and was not written by stereoseed data fetch (no {MARKER}); "
                              "move it away, or choose another folder with --dir")
    if mirrored.is_dir():  # another folder asked for: a copy of the mirror's
        return _place(sset, target, lambda staging: _copy_mirror(mirrored, staging), [f"copied from {mirrored}"])
    missing = _unverifiable(sset)
    if missing:
        raise StereoseedError(
            f"{name}: no SHA-256 recorded for {missing[0].url}" + (f" (and {len(missing) - 1} more)" if len(missing) > 1
                                                                   else "")
            + "; stereoseed does not keep a file it cannot check. Put the set in $STEREOSEED_DATA, or record the "
              "checksums of a copy checked by hand in stereoseed/io/sample_registry.py")
    downloads = root / DOWNLOADS / name
    try:
        with _disk_errors(root):
            path = _place(sset, target, lambda staging: _unpack(sset, _download_all(sset, downloads, progress),
                                                                staging), [d.url for d in sset.downloads])
        shutil.rmtree(downloads, ignore_errors=True)  # ours; the set is in place now
    finally:  # after a failure, the checked downloads stay for the next try; empty folders go
        _remove_if_empty(downloads)
        _remove_if_empty(root / DOWNLOADS)
    return path


# ---------------------------------------------------------------------------------------------
# Placing a set: staged beside its final name, renamed into place when complete


def _place(sset: SampleSet, target: Path, fill, sources: list[str]) -> Path:
    """``fill(staging)`` writes the set into a staging folder beside ``target``; then the
    registry's text files, the marker, and one rename. On any failure the staging folder goes."""
    root = target.parent
    with _disk_errors(root):
        root.mkdir(parents=True, exist_ok=True)
        _remove_stale_staging(root, sset.name)
        staging = Path(tempfile.mkdtemp(prefix=f".{sset.name}{PARTIAL}", dir=root))
    try:
        with _disk_errors(root):
            fill(staging)
            for rel, text in sset.texts.items():
                (staging / rel).write_text(text, encoding="utf-8")
            if not (staging / "SOURCE.txt").exists():
                (staging / "SOURCE.txt").write_text(_source_text(sset, sources), encoding="utf-8")
            files = sorted(p for p in staging.rglob("*") if p.is_file())
            marker = {"set": sset.name, "sources": sources,
                      "files": {p.relative_to(staging).as_posix(): _sha256(p) for p in files}}
            (staging / MARKER).write_text(json.dumps(marker, indent=1) + "\n", encoding="utf-8")
            os.chmod(staging, 0o777 & ~_umask())  # mkdtemp makes it 0700
            try:
                os.rename(staging, target)
            except OSError:
                if _complete(target):  # another fetch of the same set finished first
                    shutil.rmtree(staging)
                    return target
                raise
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    log.info("%s: wrote %s", sset.name, target)
    return target


def _umask() -> int:
    from stereoseed.io.atomic import UMASK_AT_IMPORT

    return UMASK_AT_IMPORT


def _remove_stale_staging(root: Path, name: str) -> None:
    """Staging folders of an earlier fetch of this set that was killed (only ours: by name)."""
    for old in root.glob(f".{name}{PARTIAL}*"):
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass  # not empty (another set's downloads) or not there


def _source_text(sset: SampleSet, sources: list[str]) -> str:
    listed = "\n".join(f"  {s}" for s in sources[:3]) + (f"\n  ... and {len(sources) - 3} more" if len(sources) > 3
                                                         else "")
    return (f"{sset.name}: {sset.about}.\nWritten by `stereoseed data fetch {sset.name}` from:\n{listed}\n"
            f"Every file kept was checked against the SHA-256 recorded in stereoseed/io/sample_registry.py.\n"
            f"Cite: {sset.cite}.\n")


def _copy_mirror(mirrored: Path, staging: Path) -> None:
    """The mirror's copy of the set, as it is (links followed: the mirror is the user's)."""
    shutil.copytree(mirrored, staging, dirs_exist_ok=True)
    (staging / MARKER).unlink(missing_ok=True)  # written anew for this copy


@contextmanager
def _disk_errors(root: Path) -> Iterator[None]:
    """A full disk or an unwritable folder as one line naming the folder and what to do."""
    try:
        yield
    except StereoseedError:
        raise
    except OSError as e:
        if e.errno == errno.ENOSPC:
            raise StereoseedError(f"{root}: no space left on the device; free some, or choose another folder "
                                  "with --dir") from None
        where = e.filename or root
        raise StereoseedError(f"{where}: cannot write ({e.strerror or e}); choose another folder with --dir") from None


# ---------------------------------------------------------------------------------------------
# Downloading (pooch: streamed to a temporary file, checked, then renamed)


def _download_all(sset: SampleSet, folder: Path, progress: bool) -> list[tuple[Download, Path]]:
    return [(d, _download(sset, d, folder, i, progress)) for i, d in enumerate(sset.downloads)]


def _download(sset: SampleSet, d: Download, folder: Path, index: int, progress: bool) -> Path:
    """One download, checked against its SHA-256 when the registry has it (a zip without one is
    checked member by member as it is unpacked). A file already downloaded and checked is not
    downloaded again."""
    import pooch
    import requests

    fname = f"{index:03d}-{PurePosixPath(d.url).name}"  # unique within the set, in download order
    downloader = pooch.HTTPDownloader(progressbar=progress, timeout=DOWNLOAD_TIMEOUT_S)
    try:
        with _pooch_quiet():
            return Path(pooch.retrieve(d.url, known_hash=f"sha256:{d.sha256}" if d.sha256 else None, fname=fname,
                                       path=folder, downloader=downloader))
    except requests.exceptions.RequestException as e:
        raise StereoseedError(f"{sset.name}: cannot download {d.url} ({_reason(e)}); check the connection and run "
                              f"the command again, or put the set in $STEREOSEED_DATA") from None
    except ValueError as e:  # pooch: the SHA-256 differs (the temporary file is already gone)
        raise StereoseedError(f"{sset.name}: {d.url} is not the file recorded (SHA-256 differs: {_first_line(e)}); "
                              "refused and not kept. The server may have changed it: report it") from None


def _reason(e: Exception) -> str:
    response = getattr(e, "response", None)
    if response is not None and getattr(response, "status_code", None):
        return f"HTTP {response.status_code}"
    return type(e).__name__.replace("Error", " error").strip().lower()


def _first_line(e: Exception) -> str:
    return str(e).strip().splitlines()[0][:200]


@contextmanager
def _pooch_quiet() -> Iterator[None]:
    """Pooch logs each download at INFO through a stream handler of its own; the library does
    not print (the command line shows a progress bar when asked)."""
    import pooch

    logger = pooch.get_logger()
    before = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(before)


# ---------------------------------------------------------------------------------------------
# Unpacking


def _unpack(sset: SampleSet, downloaded: list[tuple[Download, Path]], staging: Path) -> None:
    cameras: dict[str, Path] = {}
    for d, path in downloaded:
        if d.kind == "zip":
            try:
                _unzip(sset, d, path, staging)
            except StereoseedError:
                path.unlink(missing_ok=True)  # it failed its checks: not kept for a later try
                raise
        elif d.kind == "camera":
            cameras[d.dest] = path
        else:
            dest = _inside(staging, d.dest, d.url)
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, dest)
    if sset.convert == "strecha":
        convert_strecha(sset.name, staging, cameras, keep_full=sset.keep_full)
    absent = [p for p in sset.manifest if not (staging / p).is_file()]
    if absent:
        raise StereoseedError(f"{sset.name}: the downloads lack {absent[0]}" +
                              (f" (and {len(absent) - 1} more)" if len(absent) > 1 else "") + "; report it")


def _inside(staging: Path, rel: str, where: str) -> Path:
    """``staging / rel`` when ``rel`` is a plain relative path (no root, no ``..``, no backslash)."""
    parts = PurePosixPath(rel).parts
    if (not parts or PurePosixPath(rel).is_absolute() or ".." in parts or "\\" in rel or ":" in parts[0]
            or any(p in ("", ".") for p in parts)):
        raise StereoseedError(f"{where}: refused, it names {rel!r}, a path outside the set's folder")
    return staging.joinpath(*parts)


def _member_dest(sset: SampleSet, name: str) -> str | None:
    """The manifest path a zip member stands for: its own path, or under a top folder named like
    the set (the Middlebury zips unpack to NAME/...); None: not kept."""
    if name in sset.manifest:
        return name
    head, _, rest = name.partition("/")
    return rest if head == sset.name and rest in sset.manifest else None


def _check_zip(sset: SampleSet, d: Download, infos: list[zipfile.ZipInfo]) -> list[tuple[zipfile.ZipInfo, str]]:
    """The members to unpack, with their paths in the set; refused before a byte is unpacked:
    too many members, a path outside the folder, a link, a size past the bounds, a kept member
    whose declared size is not the recorded one, a member without a checksum when the zip has none."""
    where = f"{sset.name}: {d.url}"
    if len(infos) > MAX_MEMBERS:
        raise StereoseedError(f"{where}: refused, {len(infos)} members (at most {MAX_MEMBERS})")
    total = 0
    keep = []
    for info in infos:
        _inside(Path("."), info.filename.rstrip("/") or ".", where)
        mode = info.external_attr >> 16
        if stat.S_ISLNK(mode):
            raise StereoseedError(f"{where}: refused, member {info.filename!r} is a link")
        if info.file_size > MAX_MEMBER_BYTES:
            raise StereoseedError(f"{where}: refused, member {info.filename!r} declares {info.file_size} bytes "
                                  f"(at most {MAX_MEMBER_BYTES})")
        if info.compress_size and info.file_size / info.compress_size > MAX_COMPRESSION_RATIO:
            raise StereoseedError(f"{where}: refused, member {info.filename!r} unpacks to "
                                  f"{info.file_size / info.compress_size:.0f}x its size (a zip bomb?)")
        total += info.file_size
        if total > MAX_ARCHIVE_BYTES:
            raise StereoseedError(f"{where}: refused, it unpacks to more than {MAX_ARCHIVE_BYTES} bytes")
        dest = None if info.is_dir() else _member_dest(sset, info.filename)
        if dest is None:
            continue  # not part of the set (e.g. Windows' Thumbs.db): not unpacked
        if info.file_size != sset.manifest[dest][1]:
            raise StereoseedError(f"{where}: refused, {info.filename!r} declares {info.file_size} bytes, the "
                                  f"recorded file has {sset.manifest[dest][1]}")
        keep.append((info, dest))
    return keep


def _unzip(sset: SampleSet, d: Download, path: Path, staging: Path) -> None:
    where = f"{sset.name}: {d.url}"
    try:
        with zipfile.ZipFile(path) as zf:
            for info, dest in _check_zip(sset, d, zf.infolist()):
                out = _inside(staging, dest, where)
                out.parent.mkdir(parents=True, exist_ok=True)
                digest = hashlib.sha256()
                written = 0
                with zf.open(info) as src, open(out, "wb") as dst:
                    while chunk := src.read(CHUNK_BYTES):
                        written += len(chunk)
                        if written > info.file_size:  # more than it declared: stop at once
                            raise StereoseedError(f"{where}: refused, {info.filename!r} unpacks past its declared size")
                        digest.update(chunk)
                        dst.write(chunk)
                if digest.hexdigest() != sset.manifest[dest][0]:
                    raise StereoseedError(f"{where}: {info.filename!r} is not the file recorded (SHA-256 differs); "
                                          "refused and not kept. The archive may have changed: report it")
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError) as e:
        raise StereoseedError(f"{where}: not a readable zip ({e}); refused and not kept") from None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()
