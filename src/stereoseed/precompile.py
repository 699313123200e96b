"""The Numba kernels compiled once per installation: ahead (``stereoseed precompile``, which
``make`` runs), or on the first run, in helper processes while the run works.

Numba compiles a kernel on its first call and keeps the machine code in its cache
(``cache=True``; next to the package when that folder is writable, else in the user's cache
folder, or where ``NUMBA_CACHE_DIR`` says). A process compiles one kernel at a time (Numba holds
a process-wide lock while it compiles, and the GIL most of that time), so a first run compiled
its kernels one after the other, and the dense stage's worker processes each compiled the same
ones again.

:data:`KERNELS` lists every kernel a run calls from Python, with the argument types a run passes;
:data:`RUNS` the ones each kind of run calls, in the order it first calls them. On a first run
(:func:`start_compiling`) helper processes compile the ones missing from the cache in that order,
each writing to the cache, while the run goes on; a kernel the run reaches is taken from the
cache once its helper is done with it, or compiled by the run itself when no helper has started
on it. Each kernel is compiled once, by whichever process claims it first: a claim is an
exclusive lock on a file of a per-run folder, which a process that dies releases (``flock``).

A kernel's machine code, and so its results to the last bit, must not depend on which process
compiled it or what that process compiled before. It would where a Numba function that kernels
of different ``fastmath`` (or error model) call leaves that option unset: Numba gives it the
options of the caller that compiles it first (``features.image.sample_bilinear`` sets fastmath
for this reason; tests/test_precompile.py checks every function).

:func:`compile_bytecode` compiles the package's modules to bytecode (``__pycache__``): an
editable install has none until a run writes it, and a run never does where the environment
says not to (``PYTHONDONTWRITEBYTECODE``, common in containers).
"""
from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# name -> (module, function, argument types in Numba's notation): the types a run passes (every
# array C-contiguous and writable; the dense stage's arrays arrive in its workers as copies)
KERNELS: dict[str, tuple[str, str, str]] = {
    "render": ("stereoseed.synthetic.render", "render_kernel",
               ("float64[:, ::1], float64[:, ::1], float64[:, ::1], boolean, float64[::1], float64, float64[::1], "
                "int64, int64, int64, float64, float64, float64[:, ::1], float64[:, ::1], float64[:, ::1], "
                "int64[:, ::1], float64, float64, float32[:, :, ::1], float64, float32[:, :, ::1], float64, float64, "
                "float64[:, ::1], float64[::1], float64[:, ::1], float64[::1], float64")),
    "cast": ("stereoseed.synthetic.render", "cast_kernel", "float64[::1], float64[:, ::1], float64, float64"),
    "refine_camera": ("stereoseed.estimators._calibration_kernels", "refine_camera",
                      ("float64[:, ::1], float64[:, :, ::1], float64[::1], float64[:, ::1], float64[::1], "
                       "float64[:, ::1], float64[:, ::1], float64, int64")),
    "junctions": ("stereoseed.features.harris", "_junction_residual_kernel",
                  "float32[:, ::1], float32[:, ::1], float64[:, ::1], int64, float64, float64[::1]"),
    # called on OpenCV 4.x only (its remap rounds positions: features.harris._remap_is_exact)
    "sample_patches": ("stereoseed.features.harris", "_sample_patches",
                       "float32[:, ::1], float32[:, ::1], float32[:, ::1], float32[:, ::1]"),
    "edge_corners": ("stereoseed.features.edge_corners", "_edge_corner_kernel",
                     ("float32[:, ::1], float32[:, ::1], float32[:, ::1], float64[:, ::1], int64, float64, float64, "
                      "float64, float64, float64, float64, float64, float64, float64[:, ::1], boolean[::1]")),
    "repeats": ("stereoseed.geometry.neighbours", "_repeats_kernel",
                "float64[:, ::1], float64, float64[::1], float64, int64, int64[::1], int64[::1], boolean[::1]"),
    "candidate_pairs": ("stereoseed.matching._zncc_kernels", "candidate_pairs_kernel",
                        ("float64[:, ::1], float64[:, ::1], float64, float64[:, ::1], float64[::1], float64[::1], "
                         "float64")),
    "pair_scores": ("stereoseed.matching._zncc_kernels", "pair_scores",
                    ("float32[:, ::1], float32[:, :, ::1], boolean[:, ::1], int64[::1], int32[::1], float32[:, ::1], "
                     "float32[::1], float32[:, :, ::1], float32[:, ::1], float64")),
    "best_of_pairs": ("stereoseed.matching._zncc_kernels", "best_of_pairs",
                      "int64[::1], int32[::1], float32[::1], int64"),
    "align": ("stereoseed.matching._alignment_kernel", "align_kernel",
              ("float32[:, ::1], float32[:, ::1], float32[:, ::1], float32[:, ::1], float64[:, ::1], float64[:, ::1], "
               "int64, int64, float64, float64")),
    "competitors": ("stereoseed.matching._zncc_kernels", "best_competitors",
                    ("int64[::1], int32[::1], float32[::1], int64[::1], int64[::1], float64[:, ::1], float64[:, ::1], "
                     "float64")),
    "largest_angles": ("stereoseed.estimators.triangulation", "_largest_angles",
                       "float64[:, ::1], float64[:, ::1], boolean[:, ::1], float64[::1]"),
    "choose_samples": ("stereoseed.estimators._resection_kernels", "choose_samples",
                       "npy_rng, int64[:, ::1], int64[::1], boolean"),
    "score_hypotheses": ("stereoseed.estimators._resection_kernels", "score_hypotheses",
                         ("float64[:, ::1], float64[:, ::1], int64[:, ::1], float64[:, ::1], float64[:, ::1], "
                          "float64[:, ::1], float64[:, ::1], float64")),
    "nearest": ("stereoseed.geometry.neighbours", "_nearest_kernel",
                ("float64[:, ::1], float64[:, ::1], float64, float64[::1], float64, int64, int64[::1], int64[::1], "
                 "float64[::1], int64[::1]")),
    "tracks_lm": ("stereoseed.estimators.triangulation", "_tracks_lm",
                  "float64[:, :, ::1], float64[:, ::1], int64[::1], int64[::1], float64[:, ::1], int64"),
    "observation_errors": ("stereoseed.estimators.bundle", "_observation_errors",
                           ("float64[:, :, ::1], float64[:, ::1], int64[::1], int64[::1], float64[:, ::1], "
                            "float64[::1]")),
    "normal_equations": ("stereoseed.estimators._schur", "normal_equations",
                         ("float64[:, :, ::1], float64[:, ::1], int64[::1], int64[::1], float64[:, ::1], float64[::1], "
                          "int64[::1], "
                          "int64[::1], float64[:, :, :, ::1], float64, int64[::1], int64, int64, int64")),
    "eliminate_points": ("stereoseed.estimators._schur", "eliminate_points",
                         ("float64[:, :, ::1], float64[:, ::1], float64[:, ::1], float64[:, :, ::1], float64, "
                          "int64[::1], int64[::1]")),
    "add_point_pairs": ("stereoseed.estimators._schur", "_add_point_pairs",
                        ("float64[:, ::1], int64[::1], int64[::1], int64[::1], float64[:, :, ::1], float64[:, :, ::1], "
                         "int64, int64")),
    "mirror_upper": ("stereoseed.estimators._schur", "_mirror_upper", "float64[:, ::1], int64"),
    "camera_scores": ("stereoseed.estimators._schur", "camera_scores",
                      ("float64[:, :, ::1], float64[:, ::1], int64[::1], int64[::1], float64[:, ::1], float64[::1], "
                       "int64[::1], float64[:, :, :, ::1]")),
    "back_substitute": ("stereoseed.estimators._schur", "back_substitute",
                        ("float64[:, :, ::1], float64[:, ::1], float64[:, :, ::1], float64[:, ::1], int64[::1], "
                         "int64[::1]")),
    "candidate_mask": ("stereoseed.matching._zncc_kernels", "candidate_kernel",
                       ("float64[:, ::1], float64[:, ::1], float64, float64[:, ::1], float64[::1], float64[::1], "
                        "float64")),
    "window_stats": ("stereoseed.matching.propagation._kernels", "window_stats", "float64[:, ::1], int64"),
    "zncc_points": ("stereoseed.matching.propagation._kernels", "zncc_points",
                    ("float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], "
                     "int64[:, ::1], int64")),
    "propagate": ("stereoseed.matching.propagation._kernels", "propagate_kernel",
                  ("float64[:, ::1], float64[:, ::1], float64[:, ::1], boolean[:, ::1], float64[:, ::1], "
                   "float64[:, ::1], boolean[:, ::1], int64[:, ::1], float64[::1], float64, int64, int64, int64, "
                   "boolean, float64[:, ::1], float64")),
    "refine_affine": ("stereoseed.matching.propagation.refine", "_refine_affine_pass",
                      ("float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], int32[::1], int32[::1], "
                       "float64[:, ::1], boolean, float64[:, ::1], int64, float64, float64, float64, float64[::1], "
                       "float64[::1]")),
    "refine_quadratic": ("stereoseed.matching.propagation.refine", "refine_quadratic",
                         ("float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], "
                          "int32[::1], int32[::1], int32[::1], int32[::1], int64, boolean, float64[:, ::1]")),
    "two_view": ("stereoseed.estimators.triangulation", "_two_view_kernel",
                 ("float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], int64, float64[:, ::1], "
                  "float64[::1]")),
    "cell_keys": ("stereoseed.dense.grid", "_cell_keys", "float64[:, ::1], float64"),
    "grid_origin": ("stereoseed.dense.grid", "_grid_origin", "float64[:, ::1]"),
    "voxel_means": ("stereoseed.dense.densify", "_voxel_means",
                    ("int64[::1], int64[::1], float64[:, ::1], uint8[:, ::1], int64[::1], float64[:, ::1], "
                     "float64[:, ::1], uint8[:, ::1], float64[:, ::1], int64[::1], int64, int64")),
    "cells": ("stereoseed.dense.grid", "_cells", "float64[:, ::1], float64"),
    "grid_neighbours": ("stereoseed.dense.grid", "_grid_neighbours",
                        ("float64[:, ::1], int64[:, ::1], int64[::1], int64[::1], int64, float64, float64[::1], int64, "
                         "int64, int64, int32[:, ::1], int64")),
    "pca_normals": ("stereoseed.dense.normals", "pca_normals",
                    "float64[:, ::1], int32[:, ::1], int64[::1], float64[:, ::1], float64[:, ::1], int64, int64"),
    "view_checks": ("stereoseed.dense.fusion", "_check",
                    ("float64[:, ::1], int32[:, ::1], float64[::1], int64, int64[:, ::1], int32[:, :, ::1], "
                     "float64[:, :, ::1], float64[:, ::1], float64[::1], float64, float64, int64, "
                     "int64, int64[:, ::1], int64, float64[:, ::1], int32[::1], float64[::1], int32[::1], int32[::1], "
                     "int32[::1], int64, int64")),
}

# CPU seconds each kernel takes to compile alone in a fresh process on the reference machine (an
# x86-64 core; benchmarks/bench_firstrun.py measures them): what the first run's notice adds up
COST_S: dict[str, float] = {
    "render": 3.3, "cast": 0.8, "refine_camera": 5.9, "junctions": 1.0, "sample_patches": 0.4, "edge_corners": 2.6,
    "repeats": 0.9,
    "candidate_pairs": 2.4, "pair_scores": 0.7, "best_of_pairs": 0.5, "align": 7.7, "competitors": 0.6,
    "largest_angles": 0.2, "choose_samples": 1.1, "score_hypotheses": 1.3, "nearest": 0.9, "tracks_lm": 3.9,
    "observation_errors": 0.2, "normal_equations": 0.9, "eliminate_points": 0.6, "add_point_pairs": 0.3,
    "mirror_upper": 0.1, "back_substitute": 0.4, "camera_scores": 0.3, "candidate_mask": 0.4, "window_stats": 0.4, "zncc_points": 0.8,
    "propagate": 2.7, "refine_affine": 1.8, "refine_quadratic": 1.0, "two_view": 3.0, "cell_keys": 0.6,
    "grid_origin": 0.2, "voxel_means": 0.4, "cells": 0.4, "grid_neighbours": 0.6,
    "pca_normals": 0.4, "view_checks": 1.8,
}

_FEATURES = ("junctions", "sample_patches", "edge_corners", "repeats", "candidate_pairs", "pair_scores", "best_of_pairs", "align",
             "competitors", "largest_angles", "choose_samples", "score_hypotheses")
_BUNDLE = ("tracks_lm", "observation_errors", "normal_equations", "eliminate_points", "add_point_pairs",
           "mirror_upper", "back_substitute", "camera_scores")
_PROPAGATION = ("window_stats", "zncc_points", "propagate", "refine_affine", "refine_quadratic")
_FUSION = ("view_checks", "cell_keys", "grid_origin", "voxel_means", "cells", "grid_neighbours", "pca_normals")

# the kernels each kind of run calls, in the order it first calls them (the helpers compile them
# in that order, so the run finds the next one ready): "sparse" and "dense" are `stereoseed
# reconstruct` (and batch) without and with --dense (which starts the propagation's per-image
# work beside the sparse stage), "demo" and "demo-sparse" the demo on the rendered box (its pair
# calibrated first) with and without its dense stage
RUNS: dict[str, tuple[str, ...]] = {
    "sparse": _FEATURES + ("refine_camera", "nearest") + _BUNDLE + ("candidate_mask",),
    "dense": _FEATURES + ("refine_camera", "nearest") + _PROPAGATION + _BUNDLE + ("candidate_mask", "two_view")
    + _FUSION,
    "demo-sparse": ("render", "cast", "refine_camera") + _FEATURES + ("nearest",) + _BUNDLE,
    "demo": ("render", "cast", "refine_camera") + _FEATURES + ("nearest",) + _BUNDLE + _PROPAGATION
    + ("two_view",) + _FUSION,
}

_POLL_S = 0.05  # how often compile_kernels looks whether its helpers are done; a kernel takes 0.1-8 s


def kernel(name: str) -> Any:
    """The Numba dispatcher of :data:`KERNELS`' ``name`` (its module imported)."""
    import importlib

    module, function, _ = KERNELS[name]
    return getattr(importlib.import_module(module), function)


def argument_types(name: str) -> tuple:
    """The Numba types of :data:`KERNELS`' ``name``'s arguments, as a run's call resolves them."""
    from numba.core import sigutils

    args, _ = sigutils.normalize_signature(f"({KERNELS[name][2]},)")
    return tuple(args)


def missing_kernels(run: str | Iterable[str] = "dense") -> list[str] | None:
    """The kernels of ``run`` (a key of :data:`RUNS`, or kernel names) whose machine code for
    the run's argument types is not in Numba's cache (for their current source), in the run's
    order; None when the cache cannot be read (caching off, or a Numba whose cache this does not
    know)."""
    names = RUNS[run] if isinstance(run, str) else tuple(run)
    missing = []
    try:
        for name in names:
            dispatcher = kernel(name)
            cache = getattr(dispatcher._cache, "plain", dispatcher._cache)
            key = cache._index_key(argument_types(name), dispatcher.targetctx.codegen())
            if key not in cache._cache_file._load_index():
                missing.append(name)
    except Exception:  # Numba's cache internals (its version is pinned): no answer rather than a failure
        log.debug("cannot read Numba's cache index", exc_info=True)
        return None
    return missing


def kernels_cached() -> bool | None:
    """Whether Numba's cache holds every kernel of a reconstruction with its dense stage; None
    when the cache cannot be read."""
    missing = missing_kernels("dense")
    return None if missing is None else not missing


def estimated_seconds(names: Iterable[str], processes: int = 1) -> float:
    """About how long compiling the kernels ``names`` in ``processes`` processes at once takes
    on idle cores: their compile CPU seconds (:data:`COST_S`) shared among the processes, and
    no less than the costliest one."""
    costs = [COST_S.get(n, 1.0) for n in names]
    return max(sum(costs) / max(processes, 1), max(costs, default=0.0))


def _claim(path: str, wait: bool) -> int | None:
    """An open descriptor of the claim file ``path``, locked; None when ``wait`` is False and
    another process holds it (or where files cannot be locked)."""
    try:
        import fcntl
    except ImportError:  # no flock (Windows): no claims, each process compiles what it calls
        return None
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except OSError:
        os.close(fd)
        return None
    return fd


def _done(fd: int) -> bool:
    return os.pread(fd, 4, 0) == b"done"


def _finish(fd: int, seconds: float | None = None) -> None:
    """Mark a claimed kernel compiled (and how many CPU seconds it took), and release the claim."""
    os.pwrite(fd, b"done" if seconds is None else f"done {seconds:.3f}".encode(), 0)
    os.close(fd)


class _Claimed:
    """A kernel's Numba cache in a process of a run whose helpers compile ahead. Numba asks it
    for the kernel's machine code before it compiles: when the cache has none, this waits while
    another process holds the kernel's claim and then reads what that one wrote; when none
    does, it claims the kernel, this process compiles it, and the claim is released when Numba
    saves the result. Everything else goes to Numba's own cache object (``plain``)."""

    def __init__(self, plain: Any, path: str, sig: tuple):
        self.plain, self.path, self.sig, self.held = plain, path, sig, None

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        data = self.plain.load_overload(sig, target_context)
        if data is not None or self.held is not None or tuple(sig) != self.sig:
            return data
        fd = _claim(self.path, wait=True)
        if fd is None:
            return None
        if _done(fd):
            os.close(fd)
            # None when its helper could not compile it: then it is compiled here, as without helpers
            return self.plain.load_overload(sig, target_context)
        self.held = fd
        return None

    def save_overload(self, sig: Any, data: Any) -> None:
        self.plain.save_overload(sig, data)
        if tuple(sig) == self.sig:
            self.release()

    def release(self) -> None:
        if self.held is not None:
            _finish(self.held)
            self.held = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.plain, name)


def _compile_in_turn(folder: str, names: list[str], parent: int) -> None:
    """A helper process: compile each kernel of ``names`` that no process has claimed, in that
    order, noting the CPU seconds each took; those another process claimed are left to it."""
    from stereoseed.cluster import die_with_parent

    die_with_parent(parent)  # as the dense stage's workers: it dies with the run, and leaves Ctrl-C to it
    for name in names:
        fd = _claim(os.path.join(folder, name), wait=False)
        if fd is None:
            continue
        if _done(fd):
            os.close(fd)
            continue
        seconds = None
        try:
            dispatcher = kernel(name)
            if isinstance(dispatcher._cache, _Claimed):  # forked from a run that claims: compile plainly
                dispatcher._cache = dispatcher._cache.plain
            start = time.process_time()
            dispatcher.compile(argument_types(name))
            seconds = time.process_time() - start
        except Exception:  # the run compiles it itself when it calls it, and reports what fails
            log.debug("helper could not compile %s", name, exc_info=True)
        finally:
            _finish(fd, seconds)


def _turns(names: list[str], helpers: int, run_order: bool) -> list[list[str]]:
    """The order each helper goes through ``names``: with ``run_order``, every other helper in
    the run's order (the run calls them soon, one after the other) and the rest the costliest
    first (those would keep the run waiting longest, and are done before it gets to them);
    else all the costliest first (the shortest time to compile them all)."""
    costliest = sorted(names, key=lambda n: -COST_S.get(n, 1.0))
    return [names if run_order and i % 2 == 0 else costliest for i in range(helpers)]


class _Helpers:
    """The helper processes of this process's run, the claim folder they share with it and the
    dispatchers whose cache it wrapped (:class:`_Claimed`)."""

    def __init__(self, names: list[str], helpers: int, run_order: bool = True):
        from stereoseed.cluster import fork_context

        self.folder = tempfile.mkdtemp(prefix="stereoseed-compile-")
        ctx = fork_context()
        self.processes = [ctx.Process(target=_compile_in_turn, name=f"stereoseed-compile-{i}", daemon=True,
                                      args=(self.folder, turn, os.getpid()))
                          for i, turn in enumerate(_turns(names, helpers, run_order))]
        for p in self.processes:
            p.start()
        self.wrapped: list[tuple[Any, _Claimed]] = []
        for name in names:  # after the forks: a helper compiles without claims of its own
            dispatcher = kernel(name)
            if not isinstance(dispatcher._cache, _Claimed):
                claimed = _Claimed(dispatcher._cache, os.path.join(self.folder, name), argument_types(name))
                dispatcher._cache = claimed
                self.wrapped.append((dispatcher, claimed))

    def busy(self) -> bool:
        return any(p.is_alive() for p in self.processes)

    def stop(self) -> None:
        """Stop the helpers still compiling (what the run did not need), give Numba its own
        caches back and remove the claim folder."""
        for p in self.processes:
            if p.is_alive():
                p.terminate()
        for p in self.processes:
            p.join()
        for dispatcher, claimed in self.wrapped:
            claimed.release()
            if dispatcher._cache is claimed:
                dispatcher._cache = claimed.plain
        self.wrapped = []
        shutil.rmtree(self.folder, ignore_errors=True)


_running: _Helpers | None = None


def start_compiling(names: Iterable[str], helpers: int | None = None) -> bool:
    """Start compiling the kernels ``names`` (missing from the cache, in the order the run calls
    them) in ``helpers`` processes (default one per core) beside this run; they are stopped by
    :func:`stop_compiling` or when this process exits. False when they cannot help: one core, a
    platform without ``flock``, or helpers of an earlier run still compiling."""
    global _running
    from stereoseed.threads import CORES

    if _running is not None and not _running.busy():  # an earlier run's (a caller running several)
        stop_compiling()
    names = list(names)
    helpers = min(helpers or CORES, len(names))
    if _running is not None or helpers < 1 or CORES < 2 or not names:
        return False
    try:
        import fcntl  # noqa: F401
    except ImportError:
        return False
    _running = _Helpers(names, helpers)
    atexit.unregister(stop_compiling)
    atexit.register(stop_compiling)
    return True


def stop_compiling() -> None:
    """Stop this process's helpers (:func:`start_compiling`), if any."""
    global _running
    if _running is not None:
        running, _running = _running, None
        running.stop()


def compile_kernels(names: Iterable[str], helpers: int | None = None) -> dict[str, float]:
    """Compile the kernels ``names`` that the cache lacks in ``helpers`` processes (default one
    per core) and wait for them; returns the CPU seconds each took (those that failed, or were
    cached, are left out)."""
    from stereoseed.threads import CORES

    names = missing_kernels(list(names)) or []
    if not names:
        return {}
    helpers = min(helpers or CORES, len(names))
    running = _Helpers(names, helpers, run_order=False)
    try:
        while running.busy():
            time.sleep(_POLL_S)
        seconds = {}
        for name in names:
            text = Path(running.folder, name).read_bytes().decode() if Path(running.folder, name).exists() else ""
            if text.startswith("done "):
                seconds[name] = float(text.split()[1])
        return seconds
    finally:
        running.stop()


def compile_bytecode() -> bool:
    """The package's modules compiled to bytecode beside them, where they are stale or missing.
    Python then loads it whether or not it may write bytecode itself. False when some module
    could not be written (a read-only installation: then runs compile in memory, as before)."""
    import compileall
    import py_compile

    # timestamp-checked, what Python writes itself (SOURCE_DATE_EPOCH would make compileall
    # write hash-checked files, whose every import hashes the source)
    return bool(compileall.compile_dir(str(Path(__file__).resolve().parent), quiet=2,
                                       invalidation_mode=py_compile.PycInvalidationMode.TIMESTAMP))


def precompile() -> float:
    """Compile the bytecode and every kernel of :data:`KERNELS` (in one process per core), then
    run the three-image demo in a temporary folder, which calls every kernel with a real run's
    arguments (any the table misses is compiled then); returns the seconds it took."""
    from stereoseed.experiments.demo import run_demo

    t = time.perf_counter()
    compile_bytecode()
    compile_kernels(KERNELS)
    with tempfile.TemporaryDirectory(prefix="stereoseed-precompile-") as tmp:
        run_demo(Path(tmp) / "out", n_images=3, dense=True, say=lambda line: None)
    return time.perf_counter() - t
