"""Keyframes of a filmed walk: the video becomes the ordered image sequence the mapper expects.

A user who films the walk around the object has hundreds of frames a few pixels apart; the
mapper wants images that overlap well and have parallax (the paper's 10-20 degree steps). The
frames are read once, in order; Shi-Tomasi corners of the last keyframe are followed frame to
frame by pyramidal Lucas-Kanade (OpenCV), and a new keyframe is taken once they moved by
``VideoConfig.keyframe_motion`` of the image width (median), or sooner when too few of them are
still followed. Among the last frames past 3/4 of that motion, the sharpest is kept: motion blur
costs interest points. The calibrated pair stays two photos (``stereoseed reconstruct pair1.png
pair2.png walk.mp4 ...``): the video starts where the second camera stood, so its first frame is
not a keyframe.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stereoseed.io.config import VideoConfig
from stereoseed.errors import StereoseedError
from stereoseed.io.decoders import captured_stderr, decoder_detail
from stereoseed.io.files import write_image

__all__ = ["Keyframe", "KeyframePicker", "read_keyframes", "read_rig_keyframes", "sharpness"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Keyframe:
    """One frame kept: its index in the video, a name for the result folder, and either the
    uint8 BGR image or, when the keyframes were written out, its file."""

    index: int
    name: str
    image: np.ndarray | None = None
    path: Path | None = None

    @property
    def entry(self) -> Path | np.ndarray:
        """What an image sequence reads it from: its file if written, else the image."""
        return self.path if self.path is not None else self.image


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of a grey image (H, W): low for a blurred frame."""
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def _corners(gray: np.ndarray, cfg: VideoConfig) -> np.ndarray:
    pts = cv2.goodFeaturesToTrack(gray, maxCorners=cfg.tracked_points, qualityLevel=0.01, minDistance=7)
    return np.zeros((0, 1, 2), np.float32) if pts is None else pts.astype(np.float32)


class _Tracker:
    """Corners of the last keyframe followed frame to frame: how far they moved (median, px of
    the tracking scale) and which fraction of them is still followed."""

    def __init__(self, gray: np.ndarray, cfg: VideoConfig):
        self.cfg = cfg
        self.restart(gray)

    def restart(self, gray: np.ndarray) -> None:
        self.start = _corners(gray, self.cfg)
        self.current = self.start.copy()
        self.alive = np.ones(len(self.start), bool)
        self.previous = gray

    def follow(self, gray: np.ndarray) -> tuple[float, float]:
        """(median motion since the keyframe in px, fraction still followed)."""
        if len(self.start) == 0:
            self.previous = gray
            return 0.0, 0.0
        nxt, status, _ = cv2.calcOpticalFlowPyrLK(self.previous, gray, self.current, None, winSize=(21, 21),
                                                  maxLevel=3)
        self.alive &= status.ravel().astype(bool)
        self.current = nxt
        self.previous = gray
        if not self.alive.any():
            return 0.0, 0.0
        motion = np.linalg.norm((self.current - self.start)[self.alive, 0], axis=1)
        return float(np.median(motion)), float(self.alive.mean())


def read_keyframes(path: str | Path, cfg: VideoConfig = VideoConfig(), save_to: str | Path | None = None
                   ) -> list[Keyframe]:
    """The keyframes of the video at ``path``, in order (see the module's docstring). With
    ``save_to`` (a folder), each is written there as a PNG when chosen and only its file is
    kept: a long walk's keyframes never sit in memory together.

    Raises :class:`StereoseedError` when the video cannot be opened or decoded, or gives no
    keyframe (the camera did not move)."""
    return _read(Path(path), lambda p, said: _keyframes(p, cfg, save_to, said))


def read_rig_keyframes(left: str | Path, right: str | Path, cfg: VideoConfig = VideoConfig(),
                       save_to: str | Path | None = None) -> tuple[list[Keyframe], list[Keyframe]]:
    """A stereo rig's two videos, filmed together (frame k of each at the same moment): the
    keyframes chosen on the left video, its first frame included (the calibrated first
    station), and the right video's frames of the same indices. Raises
    :class:`StereoseedError` when their containers announce lengths more than a frame apart
    (containers round their count; a length one does not announce is not compared), when the
    right video ends before a keyframe of the left one, or as :func:`read_keyframes`."""
    left, right = Path(left), Path(right)
    counts = [_announced(p) for p in (left, right)]
    if min(counts) > 0 and abs(counts[0] - counts[1]) > 1:  # a frame's slack: containers round their count
        raise StereoseedError(f"{left}: {counts[0]} frames, but {right}: {counts[1]}; a rig's two videos are filmed "
                              f"together (frame k of each at the same moment): trim them to the same start and length")
    # alike names would be one file on a case-insensitive file system (Walk.mp4, walk.mp4)
    prefixes = ("left_", "right_") if left.stem.casefold() == right.stem.casefold() else ("", "")
    # the first frame is a keyframe too: the calibrated first station
    lefts = _read(left, lambda p, said: _keyframes(p, cfg, save_to, said, first=True, prefix=prefixes[0]))
    indices = [k.index for k in lefts]
    rights = _read(right, lambda p, said: _frames_at(p, indices, save_to, said, prefixes[1]))
    return lefts, rights


def _announced(path: Path) -> int:
    """The frames the container of ``path`` announces (0: unknown, or it cannot be opened)."""
    capture = _Quiet(path, [])
    try:
        return _frame_count(capture) if capture.isOpened() else 0
    finally:
        capture.release()


def _frame_count(capture) -> int:
    """The frames an open capture's container announces (0: unknown)."""
    return max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0))


def _read(path: Path, read) -> list[Keyframe]:
    """``read(path, said)`` -> (keyframes, frames decoded, frames announced), the decoder's words
    kept off the terminal and added to an error, a damaged video said."""
    if not path.is_file():
        raise StereoseedError(f"{path}: video not found")
    said: list[str] = []  # what FFmpeg and OpenCV wrote while reading (kept off the terminal)
    try:
        keyframes, frames, announced = read(path, said)
    except StereoseedError as e:
        detail = decoder_detail("".join(said), None)
        raise StereoseedError(f"{e}" + (f" (the decoder said: {detail})" if detail else "")) from None
    detail = decoder_detail("".join(said), None)
    if detail:
        log.debug("%s: the decoder said: %s", path.name, detail)
    if announced > 0 and frames < announced - 1:  # a frame's slack: containers round their count
        log.warning("%s: %d of the %d frames the file announces could be decoded: the video is damaged or cut "
                    "short after frame %d, and the walk ends there%s", path, frames, announced, frames - 1,
                    f" (the decoder said: {detail})" if detail else "")
    log.info("%s: %d keyframes of %d frames", path.name, len(keyframes), frames)
    return keyframes


class _Quiet:
    """A video capture whose calls write nothing to the terminal: what the decoder says on the
    process's stderr is added to ``said`` (each call captured on its own, so other threads'
    output is held back for a frame's decoding at most)."""

    def __init__(self, path: Path, said: list[str]):
        self.said = said
        self.capture = self._call(cv2.VideoCapture, str(path))

    def _call(self, fn, *args):
        with captured_stderr() as text:
            result = fn(*args)
        if sum(map(len, self.said)) < 4000:
            self.said.extend(text)
        return result

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self._call(self.capture.isOpened)

    def get(self, prop: int) -> float:
        return self._call(self.capture.get, prop)

    def read(self):
        return self._call(self.capture.read)

    def release(self) -> None:
        self._call(self.capture.release)


def _opened(path: Path, said: list[str]) -> _Quiet:
    capture = _Quiet(path, said)
    if not capture.isOpened():
        capture.release()
        raise StereoseedError(f"{path}: OpenCV cannot open this video (codec or container not supported); "
                              f"extract its frames into a folder (e.g. ffmpeg -i {path.name} frames/%04d.png)")
    return capture


def _kept(path: Path, index: int, frame: np.ndarray, save_to: str | Path | None, prefix: str) -> Keyframe:
    name = f"{prefix}{path.stem}_{index:06d}.png"
    if save_to is None:
        return Keyframe(index, name, frame)
    return Keyframe(index, name, path=write_image(Path(save_to) / name, frame))


def _frames_at(path: Path, indices: list[int], save_to: str | Path | None, said: list[str], prefix: str
               ) -> tuple[list[Keyframe], int, int]:
    """The frames of ``indices`` (increasing), as :func:`_keyframes` returns its keyframes (the
    frames after the last are not read, so none are announced)."""
    capture = _opened(path, said)
    wanted, kept, index = set(indices), [], -1
    try:
        while len(kept) < len(indices):
            ok, frame = capture.read()
            if not ok:
                raise StereoseedError(f"{path}: {index + 1} frames, but its rig partner's keyframe {indices[len(kept)]} "
                                      f"needs more; a rig's two videos are filmed together (frame k of each)")
            index += 1
            if index in wanted:
                kept.append(_kept(path, index, frame, save_to, prefix))
    finally:
        capture.release()
    return kept, index + 1, 0


class KeyframePicker:
    """The keyframe choice of :func:`read_keyframes`, one frame at a time (a live run reads the
    video at its own pace, :mod:`stereoseed.live`): :meth:`push` each frame in order (the first
    starts the tracking, a keyframe only with ``first``), then :meth:`end`; each returns the
    keyframes chosen by then (their frames' indices in the video), named as ``reconstruct``
    names them."""

    def __init__(self, path: str | Path, cfg: VideoConfig = VideoConfig(), save_to: str | Path | None = None,
                 first: bool = False, prefix: str = ""):
        self.path, self.cfg, self.save_to, self.first, self.prefix = Path(path), cfg, save_to, first, prefix
        self.kept = 0  # keyframes chosen so far
        self._tracker: _Tracker | None = None
        self._candidates: list[tuple[float, int, np.ndarray]] = []  # (sharpness, index, frame) past 3/4 of the motion

    def _small_gray(self, image: np.ndarray) -> np.ndarray:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return gray if self._scale == 1.0 else cv2.resize(gray, None, fx=self._scale, fy=self._scale,
                                                         interpolation=cv2.INTER_AREA)

    def _sharpest(self) -> Keyframe:
        _, best_index, best = max(self._candidates, key=lambda c: c[0])
        self._candidates = []
        self.kept += 1
        return _kept(self.path, best_index, best, self.save_to, self.prefix)

    def push(self, index: int, frame: np.ndarray) -> list[Keyframe]:
        """Frame ``index`` of the video (uint8 BGR); the keyframes it completes."""
        if self._tracker is None:
            self._scale = min(1.0, self.cfg.tracking_width / frame.shape[1])
            self._threshold = self.cfg.keyframe_motion * frame.shape[1] * self._scale
            self._tracker = _Tracker(self._small_gray(frame), self.cfg)
            if self.first:
                self.kept += 1
                return [_kept(self.path, index, frame, self.save_to, self.prefix)]
            return []
        gray = self._small_gray(frame)
        motion, followed = self._tracker.follow(gray)
        if motion >= 0.75 * self._threshold:
            self._candidates.append((sharpness(gray), index, frame))
        if motion >= self._threshold or followed < self.cfg.min_tracked_fraction or \
                len(self._candidates) >= self.cfg.sharpest_of:
            if not self._candidates:  # lost before 3/4 of the motion: this frame, as it is
                self._candidates.append((sharpness(gray), index, frame))
            self._tracker.restart(gray)
            return [self._sharpest()]
        return []

    def end(self) -> list[Keyframe]:
        """The last keyframe when the walk ended past 3/4 of a step."""
        return [self._sharpest()] if self._candidates else []


def _keyframes(path: Path, cfg: VideoConfig, save_to: str | Path | None, said: list[str], first: bool = False,
               prefix: str = "") -> tuple[list[Keyframe], int, int]:
    """(the keyframes, the number of frames decoded, the number the container announces (0:
    unknown)); what the decoder said is added to ``said``."""
    capture = _opened(path, said)
    picker = KeyframePicker(path, cfg, save_to, first, prefix)
    keyframes: list[Keyframe] = []
    announced = _frame_count(capture)
    try:
        ok, frame = capture.read()
        if not ok:
            raise StereoseedError(f"{path}: no frame could be decoded; is the file complete?")
        index = 0
        keyframes += picker.push(index, frame)
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            index += 1
            keyframes += picker.push(index, frame)
        keyframes += picker.end()
    finally:
        capture.release()
    if len(keyframes) <= first:
        raise StereoseedError(f"{path}: {index + 1} frames but no keyframe: the camera did not move by "
                              f"{100 * cfg.keyframe_motion:.0f} % of the image width")
    return keyframes, index + 1, announced
