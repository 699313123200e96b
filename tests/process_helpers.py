"""Processes of a process group, read from /proc (Linux): for the tests that kill a command and
check that none of its workers outlived it."""
from __future__ import annotations

import time
from pathlib import Path


def _live(field: int, value: int) -> list[int]:
    """Pids of the live (not zombie) processes whose /proc stat field ``field`` (after the
    command: 0 state, 1 parent pid, 2 process group) is ``value``."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[field]) == value and fields[0] != "Z":
            alive.append(int(stat.parent.name))
    return alive


def alive_in_group(pgid: int) -> list[int]:
    """Pids of the live (not zombie) processes of process group pgid."""
    return _live(2, pgid)


def children(pid: int) -> set[int]:
    """Live (not zombie) child processes of pid."""
    return set(_live(1, pid))


def wait_until(condition, timeout: float, poll: float = 0.05) -> bool:
    """Whether condition() became true within timeout seconds (polled)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll)
    return True
