"""What the command shows on the terminal: results on stdout, warnings and errors on stderr, as
log records of two loggers of their own (the library logs under ``stereoseed``; ``main`` sets how
much of that reaches stderr). The streams are looked up when a line is written, so a caller that
swaps ``sys.stdout`` (a test, a notebook) sees the lines."""
from __future__ import annotations

import errno
import io
import logging
import os
import sys
import threading

__all__ = ["say", "complain", "warn", "on_main_thread", "LibraryLines"]


def _write_line(stream, text: str) -> None:
    """``text`` as a line of its own: while a progress bar is drawn (tqdm's, on stderr), the bar
    is cleared first and drawn again below it, so that a warning is never glued to the bar's line."""
    from tqdm import tqdm

    if getattr(tqdm, "_instances", None):
        tqdm.write(text, file=stream)
    else:
        stream.write(text + "\n")
    stream.flush()


class _Stream(logging.Handler):
    """Each record's message as one line on sys.stdout (or sys.stderr), as it is at that moment."""

    def __init__(self, to_stderr: bool):
        super().__init__(logging.INFO)
        self.to_stderr = to_stderr

    def emit(self, record: logging.LogRecord) -> None:
        stream = sys.stderr if self.to_stderr else sys.stdout
        if stream is None:  # started with the stream closed (`>&-`): nobody to tell
            return
        try:
            _write_line(stream, self.format(record))
        except (BrokenPipeError, ValueError):  # the reader went away (`| head -1`), or the stream was closed
            # what the run wrote stays written: a reader that stopped reading is no error of the run's
            _to_devnull(stream)
        except OSError as e:
            if e.errno != errno.EBADF:  # a full disk under `> file` is one, and says so
                raise
            _to_devnull(stream)


class LibraryLines(_Stream):
    """The library's log records on stderr as ``stereoseed: LEVEL: message`` lines, each on a
    line of its own beside the progress bars (:func:`_write_line`)."""

    def __init__(self, level: int):
        super().__init__(to_stderr=True)
        self.setLevel(level)
        self.setFormatter(logging.Formatter("stereoseed: %(levelname)s: %(message)s"))


def _to_devnull(stream) -> None:
    """Send the rest of ``stream`` (its buffer too, flushed at exit) to the null device, so that
    neither a later line nor the interpreter's last flush fails on the closed pipe."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, stream.fileno())
        finally:
            os.close(null)
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):  # not a real file (a test's capture)
        pass


def _terminal_logger(name: str, to_stderr: bool) -> logging.Logger:
    logger = logging.getLogger(name)
    if not any(isinstance(h, _Stream) for h in logger.handlers):
        logger.addHandler(_Stream(to_stderr))
    logger.setLevel(logging.INFO)
    logger.propagate = False  # not the library's "stereoseed: LEVEL:" format, nor its --quiet
    return logger


_OUT = _terminal_logger("stereoseed.terminal.out", to_stderr=False)
_ERR = _terminal_logger("stereoseed.terminal.err", to_stderr=True)


def say(line: str) -> None:
    """A line of the command's output (stdout)."""
    _OUT.info("%s", line)


def complain(line: str) -> None:
    """A line for the user's attention (stderr): a warning, an error, a note on the run."""
    _ERR.warning("%s", line)


def on_main_thread() -> bool:
    """Whether this is the main thread: the one signals reach, and the only one that may set
    their handlers (main() is also called from tests' threads)."""
    return threading.current_thread() is threading.main_thread()


def warn(message: str) -> None:
    """``stereoseed: warning: message`` on stderr."""
    complain(f"stereoseed: warning: {message}")
