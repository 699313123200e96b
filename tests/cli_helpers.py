"""The command line as the tests run it: in this process (its exit code and what it printed) or
as a child process, and what a one-line error looks like."""
from __future__ import annotations

import sys

from stereoseed.cli import main


def run(capsys, *args) -> tuple[int, str, str]:
    """``stereoseed ARGS`` in this process: (exit code, stdout, stderr)."""
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line_error(err: str) -> bool:
    """Whether stderr is the one line of a refused input: no traceback."""
    return err.startswith("stereoseed: error: ") and err.count("\n") == 1 and "Traceback" not in err


def cli_command(*args) -> list[str]:
    """``stereoseed ARGS`` as a child process's command line (this interpreter)."""
    return [sys.executable, "-m", "stereoseed.cli", *[str(a) for a in args]]
