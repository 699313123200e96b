"""What the command shows on the terminal: results on stdout, warnings and errors on stderr, as
log records of two loggers of their own (the library logs under ``stereoseed``; ``main`` sets how
much of that reaches stderr). The streams are looked up when a line is written, so a caller that
swaps ``sys.stdout`` (a test, a notebook) sees the lines."""
from __future__ import annotations

import logging
import sys

__all__ = ["say", "complain", "warn"]


class _Stream(logging.Handler):
    """Each record's message as one line on sys.stdout (or sys.stderr), as it is at that moment."""

    def __init__(self, to_stderr: bool):
        super().__init__(logging.INFO)
        self.to_stderr = to_stderr

    def emit(self, record: logging.LogRecord) -> None:
        stream = sys.stderr if self.to_stderr else sys.stdout
        stream.write(record.getMessage() + "\n")
        stream.flush()


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


def warn(message: str) -> None:
    """``stereoseed: warning: message`` on stderr."""
    complain(f"stereoseed: warning: {message}")
