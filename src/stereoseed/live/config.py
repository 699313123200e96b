"""The live run's settings (:mod:`stereoseed.live`): how a watched folder is read and how the
page is kept up to date. The reconstruction's own settings are the run's :class:`~stereoseed.config.Config`."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.validation import positive, whole

__all__ = ["LiveConfig"]


@dataclass(frozen=True)
class LiveConfig:
    # How often the watched folder is listed (s): a fifth of a second is a small part of the
    # 1.5 s from a photo's arrival to its camera in the page, and listing a folder of a few
    # hundred files costs well under a millisecond.
    poll_s: float = 0.2
    # A file counts as written once its size and modification time have not changed for this
    # long (s) and it decodes: a phone's sync or a tethered camera writes a photo in bursts a
    # few tenths of a second apart; a file that is renamed into place is complete at once.
    stable_s: float = 0.4
    # A file whose size has settled but that does not decode is waited for this long (s), then
    # taken as unreadable (skipped with its reason, as reconstruct skips it): a copy that stalls
    # for seconds mid-file is rarer than a damaged photo, and waiting forever would hide it.
    unreadable_after_s: float = 5.0
    # A comment is sent to each page this often (s) when nothing happens: a browser that went
    # away is noticed (the write fails) and its connection closed.
    heartbeat_s: float = 5.0
    # At most this many pushed updates a second: each carries the whole 3D view (a few hundred
    # kB); photos that arrive faster are shown together in the next update.
    max_updates_per_s: float = 4.0
    # The page's log keeps the last this many lines: every update carries the log, and a walk of
    # hundreds of photos says a few lines each (the whole run's lines are in the terminal and in
    # report.json).
    log_lines: int = 200

    # --video: keyframes waiting for the run at most (each a full-size frame, ~1 MB at 640 x 480):
    # a few keep the run busy through a fast stretch of the walk; past them the reader waits
    # and then drops frames rather than holding the stream in memory.
    video_queue: int = 4
    # --video: a frame this late (s) against the stream's pace is dropped (grabbed, not decoded
    # nor tracked) until the reader is back on time; two frames at 25 fps absorb a slow decode.
    video_late_s: float = 0.08
    # --video: the frame rate assumed when the container does not give one (the usual camera's)
    video_fps: float = 25.0
    # --rig: a station's two photos written more than this many seconds apart are said (a rig
    # fires both cameras together; a camera that missed a shot pairs every later station wrong;
    # a sync tool that writes a folder late may set the times apart too, so it is said, not refused)
    station_apart_s: float = 2.0
    # --video with a camera or a stream: after a failed read, frames are waited for this long (s)
    # before the stream counts as ended (a network or USB hiccup is not the end of the walk)
    stream_gap_s: float = 5.0

    def __post_init__(self) -> None:
        positive(self, "poll_s", "stable_s", "unreadable_after_s", "heartbeat_s", "max_updates_per_s",
                 "video_late_s", "video_fps", "stream_gap_s", "station_apart_s")
        whole(self, "video_queue", "log_lines")
