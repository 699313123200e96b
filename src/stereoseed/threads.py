"""Sharing a kernel's independent rows among the cores: :func:`split_rows` and :func:`map_chunks`,
with :func:`concat_chunks` and :func:`map_items` for the common shapes of work; and
:func:`in_background`, one independent step computed while the caller goes on.

The hot loops (ZNCC scores, patch alignment, the quasi-dense refinement, the BA's reduced
camera system, dense normals) are Numba kernels that release the GIL (``nogil=True``) and treat
their rows one by one, independently. Cut into contiguous chunks, one
per core, they run in threads of one shared pool and their outputs, concatenated in order, are
the one-call outputs bit for bit. The command line keeps OpenBLAS to one thread
(:mod:`stereoseed.cli`), so these threads do not compete with BLAS's for the cores.
"""
from __future__ import annotations

import functools
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator, TypeVar

import numpy as np

__all__ = ["CORES", "current_chunks", "limit_chunks", "may_overlap", "split_rows", "map_chunks", "concat_chunks",
           "map_items", "in_background", "one_blas_thread", "with_one_blas_thread"]

T = TypeVar("T")

# The cores this process may use (its affinity, which a batch scheduler or taskset narrows)
CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_chunks = CORES  # how many chunks a kernel's rows are cut into (limit_chunks)
_in_pool = threading.local()  # .yes in the pool's own threads


def _mark_pool_thread() -> None:
    _in_pool.yes = True


def _forget_pool() -> None:
    """In a forked child: the parent's threads are not there, so neither is its pool."""
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def limit_chunks(n: int) -> None:
    """Cut kernels' rows into at most ``n`` chunks in this process (the local processes of the
    dense stage each take one core's share)."""
    global _chunks
    _chunks = max(int(n), 1)


def current_chunks() -> int:
    """How many chunks kernels' rows are cut into at most: the cores, or :func:`limit_chunks`'s."""
    return _chunks


def may_overlap() -> bool:
    """Whether work started in another thread can run beside this thread's: more than one core
    (or chunk, :func:`limit_chunks`), and this thread is not a pool thread (whose work is already
    someone's second core)."""
    return _chunks >= 2 and not getattr(_in_pool, "yes", False)


def split_rows(n: int, min_rows: int, max_chunks: int | None = None) -> np.ndarray:
    """Bounds (T + 1,) int64 cutting rows [0, n) into T contiguous chunks of nearly equal size,
    T = min(max_chunks (default: the cores, or :func:`limit_chunks`'s limit), n // min_rows) but
    at least 1: below ``min_rows`` rows a thread costs more than it saves."""
    max_chunks = _chunks if max_chunks is None else max_chunks
    chunks = int(max(1, min(max_chunks, n // max(min_rows, 1))))
    return np.linspace(0, n, chunks + 1).round().astype(np.int64)


def map_chunks(work: Callable[[int, int], T], bounds: np.ndarray) -> list[T]:
    """[work(bounds[t], bounds[t + 1]) for each chunk t], in order; the chunks after the first run
    in the shared pool's threads while the calling thread does the first (``work`` should spend
    its time in a kernel that releases the GIL). One chunk: a plain call, no thread."""
    if len(bounds) <= 2 or getattr(_in_pool, "yes", False):
        # a chunk that cuts its own rows again runs them here: queued behind itself, they would
        # wait for a pool thread that is waiting for them
        return [work(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max(CORES - 1, 1), thread_name_prefix="stereoseed-kernel",
                                       initializer=_mark_pool_thread)
    futures = [_pool.submit(work, int(a), int(b)) for a, b in zip(bounds[1:-1], bounds[2:])]
    first = work(int(bounds[0]), int(bounds[1]))
    return [first] + [f.result() for f in futures]


def concat_chunks(work: Callable[[int, int], tuple], n: int, min_rows: int) -> tuple:
    """The outputs of ``work(a, b)`` (a tuple of arrays for rows [a, b)) over rows [0, n) cut by
    :func:`split_rows` (``min_rows``), each output concatenated over the chunks in order."""
    parts = map_chunks(work, split_rows(n, min_rows))
    return tuple(parts[0]) if len(parts) == 1 else tuple(np.concatenate(out) for out in zip(*parts))


def map_items(fn: Callable[[object], T], items: tuple | list) -> list[T]:
    """[fn(item) for item in items], the items shared among the cores (``fn`` should spend its
    time in a kernel that releases the GIL)."""
    parts = map_chunks(lambda a, b: [fn(item) for item in items[a:b]], split_rows(len(items), 1))
    return [out for part in parts for out in part]


class _Deferred:
    """A Future for work run by the caller itself, the first time it asks for its result."""

    def __init__(self, fn: Callable[..., T], args: tuple):
        self._fn, self._args = fn, args
        self._future: Future | None = None

    def result(self) -> T:
        if self._future is None:
            self._future = Future()
            try:
                self._future.set_result(self._fn(*self._args))
            except Exception as e:
                self._future.set_exception(e)
        return self._future.result()


@contextmanager
def in_background(fn: Callable[..., T], *args: object) -> Iterator[Future]:
    """``fn(*args)`` started in a thread of its own while the ``with`` block goes on; the block
    takes its value with ``.result()`` (an exception of ``fn`` is raised there). Leaving the
    block waits for the thread (``fn`` must not outlive what it reads). With one core (or one
    chunk, :func:`limit_chunks`) there is no thread: ``fn`` runs when ``.result()`` is called,
    and not at all if it is not. ``fn`` should spend its time where the GIL is released
    (OpenCV, a ``nogil`` kernel) and must not change what the block reads."""
    if not may_overlap():
        yield _Deferred(fn, args)
        return
    with ThreadPoolExecutor(1, thread_name_prefix="stereoseed-background") as executor:
        yield executor.submit(fn, *args)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """OpenBLAS kept to one thread for the duration, as the command line keeps it
    (:mod:`stereoseed.cli`), for a caller of the Python API whose NumPy was loaded with OpenBLAS's
    own threads: the pipeline's linear algebra is small matrices, where those threads only spin
    against this module's (the temple in a notebook: 3.85 s and 7.0 CPU-s -> 3.34 s and 4.7 CPU-s).
    A user who set ``OPENBLAS_NUM_THREADS`` keeps their choice."""
    if "OPENBLAS_NUM_THREADS" in os.environ:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def with_one_blas_thread(fn: Callable[..., T]) -> Callable[..., T]:
    """``fn`` run under :func:`one_blas_thread` (the API's entry points)."""

    @functools.wraps(fn)
    def call(*args: object, **kwargs: object) -> T:
        with one_blas_thread():
            return fn(*args, **kwargs)

    return call
