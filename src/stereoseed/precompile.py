"""Compile the Numba kernels once, at install time: ``stereoseed precompile`` (``make`` runs it).

Numba compiles a kernel on its first call and keeps the machine code in its cache
(``cache=True``; next to the package when that folder is writable, else in the user's cache
folder, or where ``NUMBA_CACHE_DIR`` says). A fresh install would otherwise spend its first
run compiling (about 40 s on two cores). This runs the demo on three images, which calls every
kernel of rendering, interest points, matching, triangulation, bundle adjustment and the
quasi-dense stage with the argument types of a real run, and throws the result away.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path


def precompile() -> float:
    """Run the three-image demo in a temporary folder; returns the seconds it took."""
    from .demo import run_demo

    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="stereoseed-precompile-") as tmp:
        run_demo(Path(tmp) / "out", n_images=3, dense=True, say=lambda line: None)
    return time.perf_counter() - t
