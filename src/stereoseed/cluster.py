"""Where independent jobs run: in this process, in a local process pool (the default), or on an
existing Dask distributed cluster (``--scheduler tcp://HOST:PORT``, the ``cluster`` extra).

A job is a module-level function and picklable arguments (arrays, frozen configs, paths): the
local pool forks, but a Dask worker is a separate process, maybe on another machine, that gets
the job pickled. Both the dense stage (one job per image pair) and ``stereoseed batch`` (one job
per sequence) go through :func:`executor_for` and :meth:`JobPool.in_order`.

On Linux a local pool's worker is killed by the kernel when the process that started it dies
(``prctl(PR_SET_PDEATHSIG)``), so a killed caller leaves no orphaned workers behind. A worker
that dies (the OOM killer's SIGKILL) costs the job it was running one more try in a fresh pool,
and a second death ends the run with a :class:`StereoseedError`; an interrupted run does not
wait on its workers (:class:`_LocalPool`). Dask is imported only when a scheduler is given.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
# BrokenExecutor, not concurrent.futures.process's BrokenProcessPool (its subclass): that module
# is imported only when a pool starts, and every command imports this one
from concurrent.futures import BrokenExecutor, Future, InvalidStateError
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Iterator

from stereoseed.errors import StereoseedError
from stereoseed.threads import CORES, limit_chunks

__all__ = ["JobPool", "executor_for", "ProcessesBeside", "CONNECT_TIMEOUT_S"]

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10.0  # a scheduler that has not answered by then is taken as unreachable
_OTHER_DASK_SERVERS = ("Worker", "Nanny")  # the identity types of Dask's servers that are not a scheduler
_WATCH_S = 0.2  # how often a local pool's watchdog looks at its workers
_GRACE_S = 1.0  # a terminated worker that has not gone by then is killed; idle workers stop within it
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


class _OnCluster:
    """A Dask future whose ``result()`` says in one line when the cluster gave the job up (Dask
    reruns a job whose worker died, then raises ``KilledWorker`` after ``allowed-failures``)."""

    def __init__(self, future: Any, scheduler: str):
        self._future, self._scheduler = future, scheduler

    def result(self) -> Any:
        from distributed import KilledWorker  # the cluster extra: imported where it is used

        try:
            return self._future.result()
        except KilledWorker as e:
            raise StereoseedError(f"the Dask cluster at {self._scheduler} gave a job up ({getattr(e, 'task', '?')}): its "
                                  f"worker died each time it ran it; give the workers more memory, or run without "
                                  f"--scheduler") from None


@contextmanager
def executor_for(scheduler: str | None, workers: int,
                 connect_timeout: float = CONNECT_TIMEOUT_S) -> Iterator[JobPool]:
    """The :class:`JobPool` for a run: the Dask cluster whose scheduler is at ``scheduler``
    (``tcp://HOST:PORT``; its workers' threads are the slots), else ``workers`` local processes
    (1: in this process). Closed on exit: the Dask client disconnected; the local pool's idle
    workers stopped, or, when the block ends with an exception (an interrupt too), its workers
    terminated without waiting on their jobs.

    Raises :class:`StereoseedError` when Dask is not installed, when no scheduler answers at
    the address within ``connect_timeout`` seconds, or when it has no worker that can run
    stereoseed."""
    if scheduler is None:
        if workers <= 1:
            yield JobPool()
            return
        with ProcessesBeside(workers) as pool:
            yield pool
        return
    client = _connect(scheduler, connect_timeout)
    try:
        slots = sum(client.nthreads().values())
        log.info("Dask cluster at %s: %d worker threads", scheduler, slots)

        def submit(fn: Callable[..., Any], *args: Any) -> Any:
            # every job is run, none deduplicated by hash
            return _OnCluster(client.submit(fn, *args, pure=False), scheduler)

        yield JobPool(slots, submit, f"on the Dask cluster at {scheduler}", remote=True)
    finally:
        client.close()


def _connect(scheduler: str, timeout: float) -> Any:
    """A Dask client of the scheduler at ``scheduler``, with at least one worker that imports
    this stereoseed version."""
    try:
        from distributed import Client
    except ImportError:
        raise StereoseedError(_NEEDS_EXTRA) from None
    from stereoseed.cluster_probe import NotDask, ProbeError, ProbeTimeout, ask_identity

    if not scheduler.strip():
        raise StereoseedError("--scheduler: empty address; give the Dask scheduler's address, tcp://HOST:PORT")
    # probe first, with a parser of our own (cluster_probe): Dask's would unpickle whatever the
    # peer sends before we know what it is; and Dask's connect bounds the TCP connection but not
    # the handshake after it, which waits forever on a listener that does not answer (an HTTP
    # server waiting for a request line, a silent port)
    try:
        answer = ask_identity(scheduler, timeout)
    except ValueError as e:
        raise StereoseedError(f"--scheduler {scheduler}: {e}; give the Dask scheduler's address, "
                              f"tcp://HOST:PORT") from None
    except ProbeTimeout:
        raise StereoseedError(f"{scheduler}: no Dask scheduler answered within {timeout:g} s (something accepted "
                              f"the connection but did not answer Dask's handshake: another service?); check the "
                              f"port: give the address the Dask scheduler prints, tcp://HOST:PORT") from None
    except NotDask as e:
        raise StereoseedError(f"{scheduler}: that is not a Dask scheduler ({e}); give the scheduler's address "
                              f"(dask scheduler prints it), tcp://HOST:PORT") from None
    except ProbeError as e:  # refused, a name that does not resolve, closed on us
        raise StereoseedError(f"{scheduler}: no Dask scheduler answered within {timeout:g} s ({e}); "
                              f"start one (dask scheduler) and give its address, tcp://HOST:PORT") from None
    kind = answer.get("type") if isinstance(answer, dict) else None
    if kind != "Scheduler":
        # the peer's own word is not echoed (it could be anything, lines long): only Dask's other servers
        what = f"a Dask {kind}, not the scheduler" if kind in _OTHER_DASK_SERVERS else "not a Dask scheduler"
        raise StereoseedError(f"{scheduler}: that is {what}; give the scheduler's address (dask scheduler prints it), "
                              f"tcp://HOST:PORT")
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


class _Job:
    """A job of a local pool: its function and arguments, the future handed to the caller, its
    number (from 1, for messages and the board) and how many worker deaths it was charged with."""

    __slots__ = ("fn", "args", "future", "number", "deaths")

    def __init__(self, fn: Callable[..., Any], args: tuple, number: int):
        self.fn, self.args, self.future, self.number, self.deaths = fn, args, Future(), number, 0


class ProcessesBeside:
    """A :class:`JobPool` (``pool``) of ``workers`` local processes (at least one: never this
    process, for work that runs beside the caller, as a live run's dense stage behind the walk),
    each cutting its kernels' rows into ``cores_each`` chunks (default: its share of the cores).
    :meth:`close` ends it as :func:`executor_for` ends its local pool; as a context manager it
    gives the pool and abandons its jobs on an error or an interrupt."""

    def __init__(self, workers: int, cores_each: int | None = None):
        workers = max(int(workers), 1)
        self._local = _LocalPool(workers, cores_each)
        self.pool = JobPool(workers, self._local.submit, f"in {workers} local process{'es' if workers > 1 else ''}")

    def close(self, abandon: bool = False) -> None:
        """Stop the workers: once idle, or at once (``abandon``: the results are not wanted)."""
        self._local.close(abandon=abandon)

    def __enter__(self) -> JobPool:
        return self.pool

    def __exit__(self, kind: Any, value: Any, traceback: Any) -> None:
        self.close(abandon=kind is not None)


class _LocalPool:
    """``workers`` forked processes (a ``ProcessPoolExecutor``) that survive the death of one.

    A worker killed mid-job can leave the executor blind: killed while writing its result, it
    leaves the executor's manager thread in ``read()`` waiting for the rest, which no worker will
    write (the others hold the pipe open, and may wait on the dead one's lock), and the executor
    never looks at its processes again. So a watchdog thread looks at them itself. On a death (or
    the executor's own ``BrokenProcessPool``) the pool is thrown away without waiting on it
    (:func:`_throw_away`) and the jobs that were in it go to a fresh pool of half as many
    processes (fewer jobs at once, when memory was what ran out). The job the dead worker was
    running (each worker notes on a shared board the job it starts) is charged with the death:
    charged twice, it fails with a :class:`StereoseedError`; the others in the pool go again
    free. The futures handed out are the pool's own, so a job keeps its future whichever pool
    runs it."""

    def __init__(self, workers: int, cores_each: int | None = None):
        self.workers = workers
        self.cores_each = max(1, CORES // workers) if cores_each is None else max(1, int(cores_each))
        self._lock = threading.Lock()  # the executor, its processes and board, the jobs in it, closing
        self._executor: Any = None
        self._processes: dict = {}  # pid -> Process
        self._board: Any = None  # (pid, number of the last job it started) per worker, shared with them
        self._in_flight: dict[Future, _Job] = {}  # the executor's future -> the job
        self._suspect = False  # the executor reported itself broken
        self._closing = False  # no job is sent and no executor started any more
        self._closed = False  # the last executor is gone: the watchdog may go (its forks die with it)
        self._numbered = 0
        self._wake = threading.Event()
        self._watchdog: threading.Thread | None = None

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        self._numbered += 1
        job = _Job(fn, args, self._numbered)
        self._send(job)
        return job.future

    def _send(self, job: _Job) -> None:
        with self._lock:
            if self._closing:
                job.future.cancel()
                return
            if self._executor is None:
                self._start()
            try:
                inner = self._executor.submit(_noted, job.number, job.fn, *job.args)
            except BrokenExecutor as e:  # broken before the watchdog looked: it resends this one too
                inner = Future()
                inner.set_exception(e)
            self._in_flight[inner] = job
        inner.add_done_callback(self._done)  # outside the lock: a finished future calls back at once

    def _start(self) -> None:
        """A fresh executor (under the lock). Its workers are forked by the thread that submits
        first, the caller's or, after a death, the watchdog's: both live until the pool closes,
        which matters for the workers' PR_SET_PDEATHSIG."""
        from concurrent.futures import ProcessPoolExecutor  # here: every command imports this module

        ctx = fork_context()
        self._board = ctx.RawArray("q", 2 * self.workers)
        self._executor = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_start_worker,
                                             initargs=(os.getpid(), self.cores_each, self._board,
                                                       ctx.Lock()))
        # the executor's own dict (empty until it forks), kept here past its shutdown
        processes = getattr(self._executor, "_processes", None)
        self._processes = processes if processes is not None else {}
        if self._watchdog is None:
            self._watchdog = threading.Thread(target=self._watch, name="stereoseed-pool-watchdog", daemon=True)
            self._watchdog.start()

    def _done(self, inner: Future) -> None:
        """An executor's future finished (called in its manager thread): hand the outcome on,
        unless the executor broke, which is the watchdog's to handle."""
        with self._lock:
            job = self._in_flight.get(inner)
            if job is None:  # its pool was thrown away; the job went on elsewhere
                return
            if inner.cancelled() or isinstance(inner.exception(), BrokenExecutor):
                self._suspect = True
                self._wake.set()
                return
            del self._in_flight[inner]
        if inner.exception() is None:
            _settle(job.future, result=inner.result())
        else:
            _settle(job.future, inner.exception())

    def _watch(self) -> None:
        while True:
            self._wake.wait(_WATCH_S)
            self._wake.clear()
            if self._closed:
                return
            with self._lock:
                if self._closing:
                    continue
                dead = any(p.exitcode is not None for p in list(self._processes.values()))
                broken = self._executor is not None and (dead or self._suspect)
            if broken:
                self._recover()

    def _recover(self) -> None:
        """Take the broken executor and its jobs out of the pool and :meth:`_resend` them."""
        with self._lock:
            if self._closing or self._executor is None:
                return
            executor, processes, board = self._executor, self._processes, self._board
            lost = list(self._in_flight.values())
            self._executor, self._processes, self._in_flight, self._suspect = None, {}, {}, False
        try:
            self._resend(executor, processes, board, lost)
        except Exception as e:  # no fresh pool (a fork refused for want of memory...): no job may wait forever
            error = StereoseedError(f"a worker process died and no fresh one could be started ({_one_line(e)}); "
                                    f"free memory, or run with fewer worker processes (DenseConfig.workers)")
            for job in lost:
                _settle(job.future, error)

    def _resend(self, executor: Any, processes: dict, board: Any, lost: list[_Job]) -> None:
        """Throw the broken executor away, charge the death to the job the dead worker was
        running, fail the jobs charged twice and send the others to a fresh executor."""
        dead = _exit_codes(processes)
        # a broken executor SIGTERMs its other workers: those deaths are not the jobs' doing
        dead = {pid: code for pid, code in dead.items() if code != -signal.SIGTERM} or dead
        started = {board[i]: board[i + 1] for i in range(0, len(board), 2)}
        charged = [job for job in lost if job.number in {started.get(pid) for pid in dead}]
        # no job found (a worker dead in its initializer, or between jobs): all are charged, so that
        # a pool whose every worker dies ends all the same
        charged = charged or lost
        why = _death_of(list(dead.values()))
        _throw_away(executor, processes)
        for job in charged:
            job.deaths += 1
        again = [job for job in lost if job.deaths < 2]
        for job in lost:
            if job.deaths >= 2:
                _settle(job.future, StereoseedError(
                    f"a worker process died ({why}) while running job {job.number} ({_name_of(job.fn)}), for the "
                    f"second time; free memory, or run with fewer worker processes (DenseConfig.workers)"))
        if again:
            self.workers = max(1, self.workers // 2)
            log.warning("a worker process died (%s); running the %d job(s) of its pool again in %d fresh "
                        "process(es)", why, len(again), self.workers)
        for job in again:
            self._send(job)

    def close(self, abandon: bool) -> None:
        """End the pool. ``abandon`` (the caller failed or was interrupted), a job still in it or a
        dead worker: throw it away at once; else let the idle workers stop."""
        with self._lock:
            self._closing = True
            executor, processes, lost = self._executor, self._processes, list(self._in_flight.values())
            self._executor, self._processes, self._in_flight = None, {}, {}
        self._wake.set()
        for job in lost:
            job.future.cancel()
        if executor is not None:
            dead = any(p.exitcode is not None for p in list(processes.values()))
            _throw_away(executor, processes, patience=0.0 if (abandon or lost or dead) else _GRACE_S)
        self._closed = True
        self._wake.set()
        if self._watchdog is not None:
            self._watchdog.join(2.0)


def _settle(future: Future, error: BaseException | None = None, result: Any = None) -> None:
    """Give a job's future its outcome, unless it has one (cancelled by close(), failed when a
    fresh pool could not be started) already."""
    try:
        if error is None:
            future.set_result(result)
        else:
            future.set_exception(error)
    except InvalidStateError:
        pass


def _throw_away(executor: Any, processes: dict, patience: float = 0.0) -> None:
    """Shut ``executor`` down without waiting on workers that may be dead or stuck: its queued
    jobs cancelled, its workers terminated (killed after a grace period), and its result pipe's
    last write end in this process closed, so that a manager thread stuck reading a dead worker's
    half-written result gets end-of-file, gives up and exits (else the interpreter would wait on it
    at exit, forever). ``patience``: seconds the idle workers of a healthy pool get to stop by
    themselves first."""
    manager = getattr(executor, "_executor_manager_thread", None)
    results = getattr(executor, "_result_queue", None)
    executor.shutdown(wait=False, cancel_futures=True)
    try:
        if patience > 0 and manager is not None:
            manager.join(patience)
    finally:  # interrupted while waiting too: no worker may be left for the interpreter's exit to wait on
        if manager is None or manager.is_alive():
            _end_processes(list(processes.values()))
            writer = getattr(results, "_writer", None)
            if writer is not None:
                writer.close()
            if manager is not None:
                manager.join(_GRACE_S)
                if manager.is_alive():
                    log.debug("a thrown-away process pool's manager thread has not stopped yet")


def _end_processes(processes: list) -> None:
    """SIGTERM, then SIGKILL for those still there after the grace period. Waits on the
    processes' sentinels (readable once a process is gone, whoever reaps it)."""
    from multiprocessing.connection import wait

    for p in processes:
        p.terminate()
    pending = {}
    for p in processes:
        try:
            pending[p.sentinel] = p
        except ValueError:  # closed: long gone
            continue
    deadline = time.monotonic() + _GRACE_S
    try:
        while pending and (left := deadline - time.monotonic()) > 0:
            for sentinel in wait(list(pending), left):
                del pending[sentinel]
    finally:
        for p in pending.values():
            p.kill()


def _exit_codes(processes: dict) -> dict[int, int]:
    """pid -> exit code of the workers that have died. A worker whose end has begun (its
    sentinel is readable once the kernel closed its files) is not a zombie to reap yet for a
    moment: it is waited for, briefly."""
    from multiprocessing.connection import wait

    sentinels = {}
    for pid, p in list(processes.items()):
        try:
            sentinels[p.sentinel] = pid
        except ValueError:  # closed: long gone
            continue
    ending = {sentinels[s] for s in wait(list(sentinels), 0)} if sentinels else set()
    deadline = time.monotonic() + _GRACE_S
    while True:
        codes = {pid: p.exitcode for pid, p in list(processes.items()) if p.exitcode is not None}
        if ending <= codes.keys() or time.monotonic() > deadline:
            return codes
        time.sleep(0.005)


def _death_of(codes: list[int]) -> str:
    """How a worker died, from exit codes, for a message."""
    if not codes:
        return "it ended abruptly"
    code = codes[0]
    if code >= 0:
        return f"exited with code {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = "an unknown signal"
    hint = ": out of memory?" if -code == signal.SIGKILL else ""
    return f"killed by signal {-code} ({name}){hint}"


def _name_of(fn: Callable[..., Any]) -> str:
    return getattr(fn, "__qualname__", None) or getattr(fn, "__name__", None) or type(fn).__name__


_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


_board: Any = None  # in a local pool's worker: the pool's board, and this worker's place on it
_place = 0


def _start_worker(parent_pid: int, cores: int, board: Any = None, claim: Any = None) -> None:
    """Pool initializer: the worker dies with its parent, its kernels share out only its own
    part of the cores (the other workers run beside it), and it takes a free place on the
    pool's board (a pid of 0), where it notes each job it starts."""
    global _board, _place
    limit_chunks(cores)
    die_with_parent(parent_pid)
    if board is None:
        return
    with claim:
        for i in range(0, len(board), 2):
            if board[i] == 0:
                board[i] = os.getpid()
                _board, _place = board, i
                return


def _noted(number: int, fn: Callable[..., Any], *args: Any) -> Any:
    """A local pool's job as its worker runs it: noted on the board first. The note stays after
    the job: a worker killed while sending the result back is still the job's."""
    if _board is not None:
        _board[_place + 1] = number
    return fn(*args)


def fork_context():
    """The multiprocessing context of our worker processes: fork where the platform has it (the
    modules are already imported; spawn and forkserver re-run the caller's __main__, which
    breaks unguarded user scripts), else spawn."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


def die_with_parent(parent_pid: int) -> None:
    """Pool initializer: have the kernel SIGKILL this worker when its parent dies (Linux only;
    elsewhere a no-op). The signal follows the thread that started the worker, which is the one
    running the jobs' caller (or, for a pool started after a worker's death, the pool's watchdog)
    and outlives the pool. Ctrl-C is the parent's to handle: a worker
    ignores SIGINT (else every worker prints its own KeyboardInterrupt traceback). SIGTERM ends
    a worker at once: the handler a fork inherits (the CLI's raises KeyboardInterrupt) would turn
    the pool's terminate() into an exception in the job, and the worker would go on."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
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
