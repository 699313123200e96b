"""A folder watched for photos (``stereoseed live --watch DIR``): a photo is taken once it is
complete, each once, in the order it became complete (photos completed in the same look at the
folder, e.g. while an insertion ran: in the order they were written, by modification time, then
name).

A file counts as complete when its size and modification time have stayed the same for
``LiveConfig.stable_s`` and its bytes decode as an image; the bytes that were checked are the
ones handed over (the run keeps its own copy: a photo deleted or rewritten afterwards changes
nothing of the run). What the folder does otherwise is said in a line each (:attr:`Look.notes`):
a file still being written, one deleted before it was complete, one deleted after it was taken,
one that does not decode (taken as unreadable after ``LiveConfig.unreadable_after_s``: the run
skips it with its reason, as ``reconstruct`` does), a name taken already, a video.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

from stereoseed.errors import StereoseedError
from stereoseed.io.decoders import decode_image
from stereoseed.io.files import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, name_trouble
from stereoseed.live.config import LiveConfig

__all__ = ["Arrival", "Look", "FolderWatch", "RigWatch"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Arrival:
    """A complete photo: its path, name, bytes, whether they decode, when (monotonic seconds)
    the file was first seen with its final size and time, and that time (ns)."""
    path: Path
    name: str
    data: bytes
    decodes: bool
    settled_at: float
    modified_ns: int = 0


@dataclass
class Look:
    """What one look at the folder found: the photos complete since the last look, in order,
    and a line for everything else worth saying."""
    arrivals: list[Arrival] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


@dataclass
class _Pending:
    signature: tuple[int, int]  # (size, modification time in ns)
    since: float  # when it was first seen with that signature
    said_unsettled: bool = False
    said_undecodable: bool = False


class FolderWatch:
    """Looks at ``folder`` each time :meth:`look` is called. ``taken``: names already taken
    (a resumed run's), not taken again."""

    def __init__(self, folder: str | Path, cfg: LiveConfig = LiveConfig(), taken: tuple[str, ...] = ()):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise StereoseedError(f"{self.folder}: not a folder; give the folder the photos arrive in")
        self.cfg = cfg
        self.taken: set[str] = set(taken)
        self.present: set[str] = set(taken)  # taken names whose file is still there
        self._pending: dict[str, _Pending] = {}
        self._said: set[str] = set()  # names refused once (a video, a bad name, taken twice)
        self._unlisted = False  # the folder could not be listed at the last look
        self._why_unlisted = ""

    def mark_taken(self, names: list[str]) -> None:
        """``names`` were taken already (a resumed run's photos): not taken again."""
        self.taken.update(names)
        self.present.update(names)

    def give_back(self, name: str) -> None:
        """``name`` was handed over but not used (past ``--until``): not this run's."""
        self.taken.discard(name)

    def _listing(self) -> dict[str, tuple[int, int]] | None:
        """{name: (size, mtime_ns)} of the regular files in the folder, None when it cannot be listed."""
        out = {}
        try:
            with os.scandir(self.folder) as entries:
                for entry in entries:
                    if entry.name.startswith("."):  # a sync tool's temporary file, hidden
                        continue
                    try:
                        st = entry.stat()
                    except OSError:  # gone between the listing and the look
                        continue
                    if stat.S_ISREG(st.st_mode):
                        out[entry.name] = (st.st_size, st.st_mtime_ns)
        except OSError as e:
            self._why_unlisted = e.strerror or str(e)
            return None
        return out

    def look(self, now: float) -> Look:
        """The photos complete since the last look (``now``: monotonic seconds) and the notes."""
        found = Look()
        listing = self._listing()
        if listing is None:
            if not self._unlisted:  # said once, not at every look
                found.notes.append(f"{self.folder}: cannot be listed ({self._why_unlisted}); waiting for it to "
                                   f"come back")
            self._unlisted = True
            return found
        if self._unlisted:
            found.notes.append(f"{self.folder}: can be listed again")
            self._unlisted = False
        for name in sorted(self.present - listing.keys()):
            self.present.discard(name)
            found.notes.append(f"{name}: deleted from {self.folder} after it was taken; the run keeps its copy")
        for name in sorted(self._pending.keys() - listing.keys()):
            del self._pending[name]
            found.notes.append(f"{name}: deleted before it was complete; not taken")
        for name in sorted(listing):
            if name in self.taken:
                if name not in self.present and name not in self._said:
                    self._said.add(name)
                    found.notes.append(f"{name}: a photo of this name was taken already (and deleted since); "
                                       f"rename this one to add it")
                continue
            suffix = Path(name).suffix.lower()
            if suffix not in IMAGE_EXTENSIONS:
                if name not in self._said:
                    self._said.add(name)
                    what = ("a video: give it with --video" if suffix in VIDEO_EXTENSIONS
                            else "not an image by its extension")
                    found.notes.append(f"{name}: {what}; not taken")
                continue
            trouble = name_trouble(name)
            if trouble is not None:
                if name not in self._said:
                    self._said.add(name)
                    found.notes.append(f"{name}: its name holds {trouble}, which no result file can hold; "
                                       f"rename it to take it")
                continue
            arrival = self._settled(name, listing[name], now, found)
            if arrival is not None:
                self.taken.add(name)
                self.present.add(name)
                found.arrivals.append(arrival)
        found.arrivals.sort(key=lambda a: (a.modified_ns, a.name))  # a walk's order is the order of writing
        return found

    def _settled(self, name: str, signature: tuple[int, int], now: float, found: Look) -> Arrival | None:
        """The arrival of ``name`` once it is complete, else None (its state kept for the next look)."""
        pending = self._pending.get(name)
        if pending is None or pending.signature != signature:
            if pending is not None and not pending.said_unsettled:
                found.notes.append(f"{name}: still being written; waiting for it")
                pending.said_unsettled = True
            said = pending.said_unsettled if pending is not None else False
            self._pending[name] = _Pending(signature, now, said_unsettled=said)
            return None
        if now - pending.since < self.cfg.stable_s or signature[0] == 0:
            return None
        try:
            data = (self.folder / name).read_bytes()
        except FileNotFoundError:
            return None  # the next look says it was deleted
        except OSError as e:
            if not pending.said_undecodable:
                found.notes.append(f"{name}: cannot be read ({e.strerror or e}); waiting for it")
                pending.said_undecodable = True
            return None
        if len(data) != signature[0]:  # written again between the look and the read
            self._pending[name] = _Pending((len(data), signature[1]), now, pending.said_unsettled)
            return None
        decodes = decode_image(data)[0] is not None  # (what the decoders say of a half-written file: kept quiet)
        if not decodes and now - pending.since < self.cfg.unreadable_after_s:
            if not pending.said_undecodable:
                found.notes.append(f"{name}: complete in size but not decodable yet; waiting "
                                   f"{self.cfg.unreadable_after_s:g} s for the rest of it")
                pending.said_undecodable = True
            return None
        del self._pending[name]
        return Arrival(self.folder / name, name, data, decodes, pending.since, signature[1])


class RigWatch:
    """A stereo rig's two folders watched together (``--watch LEFT --rig RIGHT``): a station is
    handed over once both its photos are complete, the k-th complete photo of each side (each
    side in the order its photos were written), the left one first, as ``reconstruct --rig``
    interleaves them. Each photo's name gets its folder's name in front (``cam0_0007.jpg``;
    "left" and "right" when the folders share a name): the two cameras often name their photos
    alike, and the run keeps both in one folder."""

    def __init__(self, left: str | Path, right: str | Path, cfg: LiveConfig = LiveConfig()):
        self.cfg = cfg
        self.sides = (FolderWatch(left, cfg), FolderWatch(right, cfg))
        names = tuple(w.folder.resolve().name for w in self.sides)
        if self.sides[0].folder.resolve() == self.sides[1].folder.resolve():
            raise StereoseedError(f"{left}: the same folder for both cameras; give the right camera's photos "
                                  f"their own folder (--rig)")
        # "left" and "right" where the folders' names could make one photo's name another's
        # (cam + b_1.png and cam_b + 1.png): a name must say its side
        clash = names[0] == names[1] or names[0].startswith(names[1] + "_") or names[1].startswith(names[0] + "_")
        self.prefixes = ("left", "right") if clash else names
        self.folder = f"{self.sides[0].folder} and {self.sides[1].folder}"
        self._waiting: tuple[list[Arrival], list[Arrival]] = ([], [])

    def named(self, side: int, name: str) -> str:
        """The run's name of a photo named ``name`` in side ``side``'s folder (0: left)."""
        return f"{self.prefixes[side]}_{name}"

    def _side_of(self, name: str) -> tuple[int, str]:
        for side, prefix in enumerate(self.prefixes):
            if name.startswith(prefix + "_"):
                return side, name[len(prefix) + 1:]
        raise StereoseedError(f"{name}: a photo of the interrupted run that neither {self.sides[0].folder} nor "
                              f"{self.sides[1].folder} names ({' or '.join(p + '_' for p in self.prefixes)}...); "
                              f"resume with the folders the run watched")

    def mark_taken(self, names: list[str]) -> None:
        for name in names:
            side, own = self._side_of(name)
            self.sides[side].mark_taken([own])

    def give_back(self, name: str) -> None:
        side, own = self._side_of(name)
        self.sides[side].give_back(own)

    def look(self, now: float) -> Look:
        """The stations complete since the last look, left then right each, and both folders' notes."""
        found = Look()
        for side, watch in enumerate(self.sides):
            look = watch.look(now)
            found.notes.extend(look.notes)
            self._waiting[side].extend(dataclasses.replace(a, name=self.named(side, a.name)) for a in look.arrivals)
        complete = min(len(w) for w in self._waiting)
        for left, right in zip(self._waiting[0][:complete], self._waiting[1][:complete]):
            found.arrivals += [left, right]
            apart = abs(left.modified_ns - right.modified_ns) / 1e9
            if apart > self.cfg.station_apart_s:  # a camera that missed a shot shifts every station after
                found.notes.append(f"{left.name} and {right.name}, paired as one station, were written {apart:.0f} s "
                                   f"apart: if a camera missed a shot, the stations from here are paired wrong; "
                                   f"stop and give the photos to reconstruct --rig in their pairs")
        for waiting in self._waiting:
            del waiting[:complete]
        ahead = len(self._waiting[0]) - len(self._waiting[1])
        if abs(ahead) >= 2:
            side = 0 if ahead > 0 else 1
            found.notes.append(f"{self.sides[side].folder}: {abs(ahead)} photos wait for the other camera's "
                               f"({self.sides[1 - side].folder})")
        return found
