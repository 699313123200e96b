"""The photos a run read, recorded beside its result (``inputs.json``) so the exports that need
them (the hand-offs of :mod:`stereoseed.output.handoff`) find them without being told again.

Per input image, in cameras.json's order: ``name`` (as cameras.json), ``path`` (the photo
relative to the result folder, so a result moved together with its photos still finds them),
``absolute`` (the photo's absolute path when the run read it, so a result moved alone still
finds them), ``bytes`` and ``sha256`` (the file as the run read it: a photo changed since is
refused, never handed off under the run's cameras). A rig walk's images also carry ``side``
(``left``/``right``) and ``original_name`` (the file's own name: ``cam0/7.jpg`` is ``cam0_7.jpg``
in the result). A video's keyframes are the result's own ``keyframes/`` files. An image the run
got in memory has ``path`` null. A result folder without inputs.json (written before it
existed) needs ``--images`` as it always did.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

from stereoseed.errors import StereoseedError
from stereoseed.io.files import write_json

__all__ = ["INPUTS_FILE", "INPUTS_VERSION", "write_inputs", "recorded_photos", "renamed_photos", "file_digest"]

log = logging.getLogger(__name__)

INPUTS_FILE = "inputs.json"
INPUTS_VERSION = 1
# read a chunk at a time: a long sequence's photos (or a 3 GB file) are never held whole
_HASH_CHUNK = 1 << 20
_AGAIN = "give --images DIR with the photos the run read"


def file_digest(path: str | Path) -> tuple[int, str]:
    """(Byte size, SHA-256 hex digest) of the file at ``path``, read a chunk at a time."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(_HASH_CHUNK):
            h.update(chunk)
            size += len(chunk)
    return size, h.hexdigest()


def _entry(source: str, name: str, staging: Path, final: Path) -> dict:
    """One image's record: ``source`` as the run read it ("memory" for an array)."""
    if source == "memory":
        return {"name": name, "path": None}
    path = Path(source).resolve()
    try:  # the run's own files (a video's keyframes) are in the staging folder until it is swapped in
        absolute, relative = final / path.relative_to(staging), path.relative_to(staging).as_posix()
    except ValueError:
        absolute = path
        try:
            relative = Path(os.path.relpath(path, final)).as_posix()
        except ValueError:  # no relative path between them (another drive on Windows)
            relative = None
    try:
        size, digest = file_digest(path)
    except OSError as e:  # a photo the run skipped as unreadable: recorded, never found as the one read
        log.warning("%s: not hashed for %s (%s)", path, INPUTS_FILE, e.strerror or e)
        size, digest = None, None
    return {"name": name, "path": relative, "absolute": str(absolute), "bytes": size, "sha256": digest}


def write_inputs(folder: str | Path, final: str | Path, sources: list[str], names: list[str],
                 rig: bool = False) -> Path:
    """Write ``folder``/inputs.json for the images read from ``sources`` (one path a name, in
    cameras.json's order), its paths relative to ``final``: where the folder will stand (a
    run writes into a staging folder swapped in at the end). Each photo is read once more to
    hash it: the run has just read it (the checkpoint's fingerprint), so it comes from the
    disk cache, about a millisecond per megabyte."""
    folder, final = Path(folder).resolve(), Path(final).resolve()
    images = []
    for i, (source, name) in enumerate(zip(sources, names)):
        entry = _entry(source, name, folder, final)
        if rig:  # a rig walk interleaves its sides: left, right, left, ...
            entry.update(side="right" if i % 2 else "left",
                         original_name=None if source == "memory" else Path(source).name)
        images.append(entry)
    return write_json(folder / INPUTS_FILE, {"format_version": INPUTS_VERSION, "images": images})


def _read(folder: Path, names: list[str]) -> list[dict] | None:
    """inputs.json's images, checked against cameras.json's ``names``; None when there is none."""
    path = folder / INPUTS_FILE
    if not path.is_file():
        return None
    try:
        images = json.loads(path.read_text(encoding="utf-8"))["images"]
        ok = isinstance(images, list) and all(isinstance(e, dict) and all(
            isinstance(e.get(k), (str, type(None))) for k in ("path", "absolute", "sha256", "original_name"))
            and isinstance(e.get("bytes"), (int, type(None))) for e in images)
    except (OSError, ValueError, KeyError, TypeError):
        ok = False
    if not ok or [e.get("name") for e in images] != names:
        raise StereoseedError(f"{path}: not the record of this result's images (malformed, or naming others than "
                              f"cameras.json); {_AGAIN}")
    return images


def recorded_photos(folder: str | Path, names: list[str], indices: list[int]) -> dict[int, Path] | None:
    """The photo of each image of ``indices`` as the result folder's inputs.json records it
    (its relative path first, then its absolute one), checked to be the file the run read (its
    byte size and SHA-256); None when the folder has no record. Raises :class:`StereoseedError`
    naming the first image whose photo is missing or changed."""
    folder = Path(folder)
    images = _read(folder, names)
    if images is None:
        return None
    photos = {}
    for i in indices:
        entry = images[i]
        places = [Path(os.path.normpath(folder / entry["path"])) if entry.get("path") else None,
                  Path(entry["absolute"]) if entry.get("absolute") else None]
        path = next((p for p in places if p is not None and p.is_file()), None)
        if path is None:
            where = " or ".join(str(p) for p in places if p is not None) or "memory (not on disk)"
            raise StereoseedError(f"{names[i]}: its photo is not at {where} (recorded in {folder / INPUTS_FILE}); "
                                  f"{_AGAIN}")
        size, digest = file_digest(path)
        if (size, digest) != (entry.get("bytes"), entry.get("sha256")):
            how = f"{size} bytes, the run read {entry.get('bytes')}" if size != entry.get("bytes") else "other bytes"
            raise StereoseedError(f"{names[i]}: the photo at {path} has changed since the run read it ({how}); "
                                  f"{_AGAIN}")
        photos[i] = path
    log.debug("found %d photos through %s", len(photos), folder / INPUTS_FILE)
    return photos


def renamed_photos(folder: str | Path, names: list[str], indices: list[int], paths: list[Path]) -> dict[int, Path]:
    """Among ``paths`` (the photos --images gives), the photo of each image of ``indices`` that
    the run renamed (a rig's ``cam0/7.jpg`` is ``cam0_7.jpg``): the file of its recorded
    ``original_name`` whose byte size and SHA-256 are the recorded ones (both sides may hold a
    ``7.jpg``: the content tells them apart). Images the record does not rename, or whose photo
    is not among ``paths``, are left out; so is every image of a folder without a record."""
    images = _read(Path(folder), names)
    if images is None:
        return {}
    by_name: dict[str, list[Path]] = {}
    for p in paths:
        by_name.setdefault(p.name, []).append(p)
    digests: dict[Path, tuple[int, str]] = {}
    photos = {}
    for i in indices:
        entry = images[i]
        for p in by_name.get(entry.get("original_name") or "", []):
            if p not in digests:
                digests[p] = file_digest(p)
            if digests[p] == (entry.get("bytes"), entry.get("sha256")):
                photos[i] = p
                break
    return photos
