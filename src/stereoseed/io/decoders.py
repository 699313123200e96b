"""What the image decoders (libpng, libjpeg, OpenCV) print, kept off the terminal and turned into
one line of a message; and the decoding of an image's bytes under that guard."""
from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading

import cv2
import numpy as np

__all__ = ["captured_stderr", "decoder_detail", "decode_image", "one_line"]


def one_line(text: str, limit: int = 80) -> str:
    """``text`` for a one-line message: non-printable characters escaped, shortened."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[: limit + 1])
    return text if len(text) <= limit else text[:limit] + "..."


# One redirection of file descriptor 2 at a time: the images are read in background threads
# too (the mapper's prefetching), and two overlapping redirections would each save and restore
# the other's temporary file, leaving the process's stderr (progress bars, error lines) pointed
# at a deleted file for the rest of the run.
_STDERR_LOCK = threading.RLock()  # re-entrant: a nested capture in one thread nests properly


@contextlib.contextmanager
def captured_stderr():
    """Route the process's standard error (file descriptor 2, where libpng, libjpeg and OpenCV's
    log write) to a temporary file for the block; yields a list that then holds what was written.
    Anything another thread writes to stderr meanwhile is captured too (decoding takes ms);
    threads capturing at once take turns (:data:`_STDERR_LOCK`)."""
    captured: list[str] = []
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):
            yield captured  # no file descriptor 2 to redirect (embedded interpreter): leave it
            return
        try:
            with tempfile.TemporaryFile() as tmp:
                os.dup2(tmp.fileno(), 2)
                try:
                    yield captured
                finally:
                    os.dup2(saved, 2)
                    tmp.seek(0)
                    captured.append(tmp.read(4000).decode("utf-8", "replace"))
        finally:
            os.close(saved)


_CV_LOG_PREFIX = re.compile(r"^\[\s*\w+:[^\]]*\]\s*(?:global\s+)?\S+:\d+\s+\S+\s+")


def decoder_detail(stderr_text: str, error: Exception | None) -> str:
    """What the decoders said, as a short one-line text ('' when nothing)."""
    said = [_CV_LOG_PREFIX.sub("", ln).strip() for ln in stderr_text.splitlines()]
    if error is not None:
        text = str(error)
        if "CV_IO_MAX_IMAGE_PIXELS" in text:
            said.append("more pixels than OpenCV decodes (CV_IO_MAX_IMAGE_PIXELS)")
        else:
            m = re.search(r"\)\s*(.*?)\s+in function", text, re.S)
            said.append(m.group(1) if m else "OpenCV error")
    return one_line("; ".join(dict.fromkeys(s for s in said if s)), 160)



def decode_image(data: bytes) -> tuple[np.ndarray | None, str]:
    """The image (H, W, 3) uint8 BGR the bytes ``data`` decode to (``cv2.imdecode``), or None,
    and what the decoders said of them (kept off the terminal; empty when nothing), for a message."""
    error = None
    with captured_stderr() as stderr_text:
        try:
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error as e:
            image, error = None, e
    if image is not None and image.size == 0:
        image = None
    return image, decoder_detail("".join(stderr_text), error)
