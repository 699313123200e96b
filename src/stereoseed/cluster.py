"""Where independent jobs run: in this process, in a local process pool (the default), or on an
existing Dask distributed cluster (``--scheduler tcp://HOST:PORT``, the ``cluster`` extra).

A job is a module-level function and picklable arguments (arrays, frozen configs, paths): the
local pool forks, but a Dask worker is a separate process, maybe on another machine, that gets
the job pickled. Both the dense stage (one job per image pair) and ``stereoseed batch`` (one job
per sequence) go through :func:`executor_for` and :meth:`JobPool.in_order`.

On Linux a local pool's worker is killed by the kernel when the process that started it dies
(``prctl(PR_SET_PDEATHSIG)``), so a killed caller leaves no orphaned workers behind. Dask is
imported only when a scheduler is given.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
from collections import deque
from concurrent.futures import Future
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator

from stereoseed.errors import StereoseedError
from stereoseed.threads import CORES, limit_chunks

__all__ = ["JobPool", "executor_for", "CONNECT_TIMEOUT_S"]

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10.0  # a scheduler that has not answered by then is taken as unreachable
_NEEDS_EXTRA = "--scheduler needs the cluster extra: pip install 'stereoseed[cluster]'"


class JobPool:
    """Runs jobs ``fn(*args)`` and hands back futures (``.result()`` returns the value or raises
    the job's exception). ``slots``: how many jobs run at once; ``remote``: the jobs run on a
    Dask cluster (whose worker processes cannot start a pool of their own); ``where``: for
    messages ("in this process", "on the Dask cluster at ...")."""

    def __init__(self, slots: int = 1, submit: Callable[..., Any] | None = None, where: str = "in this process",
                 remote: bool = False):
        self.slots, self.where, self.remote = max(1, slots), where, remote
        self._submit = submit

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self._submit is not None:
            return self._submit(fn, *args)
        done: Future = Future()  # in this process: run now, hand back a finished future
        try:
            done.set_result(fn(*args))
        except Exception as e:  # the caller's .result() raises it, as a pool's future does
            done.set_exception(e)
        return done

    def in_order(self, fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]:
        """The future of ``fn(job)`` for each job, in the order of ``jobs``, whichever finishes
        first: what the caller builds from the results (a fused cloud, a summary) never depends
        on timing. Jobs are drawn lazily and at most two per slot are in flight, which bounds
        the memory held by inputs and finished results (one pair's cloud is megabytes)."""
        window = 2 * self.slots if self._submit is not None else 1
        in_flight: deque = deque()
        for job in jobs:
            in_flight.append(self.submit(fn, job))
            if len(in_flight) >= window:
                yield in_flight.popleft()
        while in_flight:
            yield in_flight.popleft()


@contextmanager
def executor_for(scheduler: str | None, workers: int,
                 connect_timeout: float = CONNECT_TIMEOUT_S) -> Iterator[JobPool]:
    """The :class:`JobPool` for a run: the Dask cluster whose scheduler is at ``scheduler``
    (``tcp://HOST:PORT``; its workers' threads are the slots), else ``workers`` local processes
    (1: in this process). Closed (the local pool joined, the Dask client disconnected) on exit.

    Raises :class:`StereoseedError` when Dask is not installed, when no scheduler answers at
    the address within ``connect_timeout`` seconds, or when it has no worker that can run
    stereoseed."""
    if scheduler is None:
        if workers <= 1:
            yield JobPool()
            return
        # fork where the platform has it: spawn/forkserver re-run the caller's __main__, which
        # breaks unguarded user scripts
        from concurrent.futures import ProcessPoolExecutor  # here: every command imports this module

        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_start_worker,
                                 initargs=(os.getpid(), max(1, CORES // workers))) as pool:
            yield JobPool(workers, pool.submit, f"in {workers} local processes")
        return
    client = _connect(scheduler, connect_timeout)
    try:
        slots = sum(client.nthreads().values())
        log.info("Dask cluster at %s: %d worker threads", scheduler, slots)

        def submit(fn: Callable[..., Any], *args: Any) -> Any:
            return client.submit(fn, *args, pure=False)  # every job is run, none deduplicated by hash

        yield JobPool(slots, submit, f"on the Dask cluster at {scheduler}", remote=True)
    finally:
        client.close()


def _connect(scheduler: str, timeout: float) -> Any:
    """A Dask client of the scheduler at ``scheduler``, with at least one worker that imports
    this stereoseed version."""
    try:
        import asyncio

        from distributed import Client
        from distributed.comm import connect
    except ImportError:
        raise StereoseedError(_NEEDS_EXTRA) from None
    if not scheduler.strip():
        raise StereoseedError("--scheduler: empty address; give the Dask scheduler's address, tcp://HOST:PORT")

    async def probe() -> None:
        comm = await connect(scheduler, timeout=timeout)
        await comm.close()

    # probe first: a Client whose connection failed still tries to close itself when it is
    # garbage-collected, seconds later, with a traceback on stderr
    try:
        asyncio.run(probe())
    except Exception as e:  # refused, timed out, a bad address, something else answering there
        raise StereoseedError(f"{scheduler}: no Dask scheduler answered within {timeout:g} s ({_one_line(e)}); "
                              f"start one (dask scheduler) and give its address, tcp://HOST:PORT") from None
    client = Client(scheduler, timeout=timeout, set_as_default=False)
    try:
        _check_workers(client, scheduler, timeout)
    except BaseException:
        client.close()
        raise
    return client


def _check_workers(client: Any, scheduler: str, timeout: float) -> None:
    """Refuse a cluster whose jobs would wait forever (no worker) or fail one by one (a worker
    without stereoseed, or with another version of it)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        raise StereoseedError(f"{scheduler}: the scheduler has no worker; start some (dask worker {scheduler})") from None
    try:
        mine = version("stereoseed")
    except PackageNotFoundError:  # run from a source tree: nothing to compare the workers with
        return
    # importlib's own function, not one of ours: a worker without stereoseed could not unpickle that
    theirs = client.run(version, "stereoseed", on_error="return")
    wrong = {w: v for w, v in theirs.items() if v != mine}
    if wrong:
        worker, found = next(iter(wrong.items()))
        found = found if isinstance(found, str) else "(not installed)"
        raise StereoseedError(f"{scheduler}: worker {worker} has stereoseed {found}, this machine {mine}; "
                              f"install the same version on every worker")


def _one_line(e: object) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _start_worker(parent_pid: int, cores: int) -> None:
    """Pool initializer: the worker dies with its parent and its kernels share out only its own
    part of the cores (the other workers run beside it)."""
    limit_chunks(cores)
    _die_with_parent(parent_pid)


def _die_with_parent(parent_pid: int) -> None:
    """Pool initializer: have the kernel SIGKILL this worker when its parent dies (Linux only;
    elsewhere a no-op). The signal follows the thread that started the worker, which is the one
    running the jobs' caller and outlives the pool. Ctrl-C is the parent's to handle: a worker
    ignores SIGINT (else every worker prints its own KeyboardInterrupt traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # no libc prctl: keep the worker, as before
        return
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)
