"""A filmed walk as a live source (``stereoseed live --video FILE``, or a camera or a stream
filmed now: ``--video 0``, ``--video rtsp://...``): the video read at its own pace (a file at its
frame rate, as if filmed now; a camera or a stream as it delivers its frames) in a thread, each frame given to the keyframe
choice of ``reconstruct`` (:class:`stereoseed.io.video.KeyframePicker`), the keyframes handed to
the run through a bounded queue.

When the run falls behind (the queue is full), the reader waits; a stream cannot wait, so the
frames that came meanwhile are dropped (grabbed, not decoded) until the reader is back at the
stream's pace, and the drop is said: with frames dropped the keyframes may differ from
``reconstruct``'s on the same video (the tracking jumped). With none dropped they are the same
frames, named alike, so the result is ``reconstruct``'s on the pair's photos and the video.

A camera or a stream cannot be read again: its keyframes are named after it and the time the
reading started (``camera0_20261207-191500_000123.png``), so a resumed run's new keyframes never
take the names of the interrupted run's.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path

import cv2

from stereoseed.errors import StereoseedError
from stereoseed.io.config import VideoConfig
from stereoseed.io.decoders import captured_stderr
from stereoseed.io.video import KeyframePicker
from stereoseed.live.config import LiveConfig
from stereoseed.live.watch import Arrival, Look

__all__ = ["VideoFeed", "stream_source"]

log = logging.getLogger(__name__)


def stream_source(video: str | Path) -> int | str | None:
    """What OpenCV opens for ``video`` when it is a camera or a stream filmed now: a camera's
    number (``"0"``: the first camera, unless a file of that name is there) or a URL (``rtsp://``,
    ``http://``...); None for a file."""
    text = str(video)
    if Path(text).is_file():  # a file named 0 is a file
        return None
    if text.isdigit():
        return int(text)
    return text if "://" in text else None


class VideoFeed:
    """Keyframes of the video at ``path`` as they are chosen (:meth:`look`, as a watched
    folder's arrivals). ``realtime`` False: read as fast as the run takes them (a test)."""

    def __init__(self, path: str | Path, cfg: VideoConfig = VideoConfig(), live: LiveConfig = LiveConfig(),
                 realtime: bool = True):
        stream = stream_source(path)
        if stream is None:
            self.path = Path(path)
            if not self.path.is_file():
                raise StereoseedError(f"{self.path}: video not found")
            self._capture = cv2.VideoCapture(str(self.path))
            if not self._capture.isOpened():
                raise StereoseedError(f"{self.path}: cannot be opened as a video; give a video OpenCV reads (MP4, AVI, "
                                      f"MKV)")
        else:
            # the keyframes' names: the camera's number or the stream's last path part, and when
            # the reading started (a stream read again is another one)
            what = f"camera{stream}" if isinstance(stream, int) else (Path(stream.split("?")[0]).stem or "stream")
            self.path = Path(f"{what}_{time.strftime('%Y%m%d-%H%M%S')}")
            with captured_stderr():  # OpenCV's own warnings of a missing camera: the line below says it
                self._capture = cv2.VideoCapture(stream)
            if not self._capture.isOpened():
                why, check = (("no such camera", "the camera's number") if isinstance(stream, int) else
                              ("the stream does not answer or is not a video OpenCV reads", "the address"))
                raise StereoseedError(f"{path}: cannot be opened ({why}); check {check}")
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and 1.0 <= fps <= 1000.0 else live.video_fps
        # a camera or a stream delivers its frames at its own pace: read as they come (its own
        # buffer drops what the run cannot take), not against a clock of the fps it reports, which
        # would take every frame after a slow one for a late one and drop them all
        self.stream = stream
        self.live, self.realtime = live, realtime and stream is None
        self._picker = KeyframePicker(self.path, cfg)
        self._queue: queue.Queue = queue.Queue(maxsize=live.video_queue)
        self._notes: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self.ended = threading.Event()
        self.frames = self.dropped = 0
        self._thread = threading.Thread(target=self._read, name="stereoseed-live-video", daemon=True)

    def start(self) -> VideoFeed:
        self._thread.start()
        return self

    def mark_taken(self, names: list[str]) -> None:
        """(As a watched folder's; nothing to do: a resumed video run reads again from its start
        and the run skips the keyframes it holds.)"""

    def give_back(self, name: str) -> None:
        """(As a watched folder's; nothing to do: a keyframe past ``--until`` is dropped with the
        rest of the video.)"""

    def _put(self, arrival: Arrival) -> None:
        """Into the queue, waiting while it is full (the run is behind)."""
        while not self._stop.is_set():
            try:
                self._queue.put(arrival, timeout=0.1)
                return
            except queue.Full:
                continue

    def _read(self) -> None:
        t0, index, dropped_since = time.monotonic(), -1, 0
        try:
            while not self._stop.is_set():
                due = t0 + (index + 1) / self.fps
                late = time.monotonic() - due
                if self.realtime and late < 0:
                    time.sleep(-late)
                if self.realtime and index >= 0 and late > self.live.video_late_s:
                    if not self._capture.grab():  # behind the stream: this frame is dropped
                        break
                    index += 1
                    self.dropped += 1
                    dropped_since += 1
                    continue
                if dropped_since:
                    self._notes.put(f"{self.path.name}: {dropped_since} frame(s) dropped while the run was behind "
                                    f"(before frame {index + 1}); the keyframes may differ from reconstruct's")
                    dropped_since = 0
                ok, frame = self._capture.read()
                if not ok and self.stream is not None:
                    ok, frame = self._next_after_a_gap()
                if not ok:
                    break
                index += 1
                self.frames += 1
                for keyframe in self._picker.push(index, frame):
                    self._put(self._arrival(keyframe))
            for keyframe in self._picker.end():
                self._put(self._arrival(keyframe))
            self._notes.put(f"{self.path.name}: the stream ended after {index + 1} frames "
                            f"({self._picker.kept} keyframes)")
        except Exception as e:  # noqa: BLE001 - a decoder error ends the stream, said
            log.debug("video reader", exc_info=True)
            self._notes.put(f"{self.path.name}: the stream stopped ({e}); what came is kept")
        finally:
            self._capture.release()
            self.ended.set()

    def _next_after_a_gap(self) -> tuple[bool, object]:
        """A camera's or a stream's next frame after a failed read: tried again for
        ``LiveConfig.stream_gap_s`` (a network or USB hiccup is not the end of the walk)."""
        self._notes.put(f"{self.path.name}: no frame; waiting up to {self.live.stream_gap_s:g} s for the stream")
        until = time.monotonic() + self.live.stream_gap_s
        while time.monotonic() < until and not self._stop.is_set():
            time.sleep(0.1)
            ok, frame = self._capture.read()
            if ok:
                self._notes.put(f"{self.path.name}: frames again")
                return ok, frame
        return False, None

    def _arrival(self, keyframe) -> Arrival:
        ok, png = cv2.imencode(".png", keyframe.image)  # lossless: the pixels reconstruct's keyframes hold
        return Arrival(self.path, keyframe.name, png.tobytes(), bool(ok), time.monotonic())

    def look(self, now: float) -> Look:
        """The keyframes chosen since the last look, and the lines to say."""
        found = Look()
        while True:
            try:
                found.arrivals.append(self._queue.get_nowait())
            except queue.Empty:
                break
        while True:
            try:
                found.notes.append(self._notes.get_nowait())
            except queue.Empty:
                break
        return found

    @property
    def done(self) -> bool:
        """The stream has ended and every keyframe was taken."""
        return self.ended.is_set() and self._queue.empty()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
