"""Compile the Numba kernels and the package's bytecode once, at install time: ``stereoseed
precompile`` (``make`` runs it).

Numba compiles a kernel on its first call and keeps the machine code in its cache
(``cache=True``; next to the package when that folder is writable, else in the user's cache
folder, or where ``NUMBA_CACHE_DIR`` says). A fresh install would otherwise spend its first
run compiling (about 40 s on two cores). This runs the demo on three images, which calls every
kernel of rendering, interest points, matching, triangulation, bundle adjustment and the
quasi-dense stage with the argument types of a real run, and throws the result away.

It first compiles the package's modules to bytecode (``__pycache__``): an editable install has
none until a run writes it, and a run never does where the environment says not to
(``PYTHONDONTWRITEBYTECODE``, common in containers). Each run then compiled the package's 64
modules again, 0.1-0.25 s of every command on two cores.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path


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


def kernels_cached() -> bool | None:
    """Whether Numba's cache holds machine code of the first kernel a reconstruction calls (the
    interest points') for its current source: False after a fresh install until a run or
    :func:`precompile` compiled them (the first run then spends about a minute compiling);
    None when the cache cannot be read."""
    try:
        from stereoseed.features.edge_corners import _edge_corner_kernel

        return bool(_edge_corner_kernel._cache._cache_file._load_index())
    except Exception:  # Numba's cache internals (its version is pinned): no answer rather than a failure
        return None


def precompile() -> float:
    """Compile the bytecode and run the three-image demo in a temporary folder; returns the
    seconds it took."""
    from stereoseed.experiments.demo import run_demo

    t = time.perf_counter()
    compile_bytecode()
    with tempfile.TemporaryDirectory(prefix="stereoseed-precompile-") as tmp:
        run_demo(Path(tmp) / "out", n_images=3, dense=True, say=lambda line: None)
    return time.perf_counter() - t
