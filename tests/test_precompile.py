"""The kernels compiled once per installation (``stereoseed precompile``, or helper processes
beside a first run), the first-run notice, the progress bar's rate, and the bytecode."""
from __future__ import annotations

import importlib
import importlib.util
import io
import json
import os
import pkgutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

from cli_helpers import cli_command
from process_helpers import alive_in_group, wait_until

import stereoseed
from stereoseed import precompile
from stereoseed.cli import _progress
from stereoseed.precompile import compile_bytecode


def _python(code: str, tmp_path: Path, cache: Path | None = None, timeout: float = 120.0,
            **popen) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (the kernels' cache in ``cache`` when given)."""
    env = dict(os.environ)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=timeout, **popen)


def test_every_module_gets_current_bytecode_even_where_imports_may_not_write_it(monkeypatch):
    """A container commonly sets PYTHONDONTWRITEBYTECODE: without bytecode beside the sources
    every command would compile the whole package again."""
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")  # a reproducible-build setting: still timestamp-checked files
    package = Path(stereoseed.__file__).resolve().parent
    probe = package / "arrays.py"
    cached = Path(importlib.util.cache_from_source(str(probe)))
    cached.unlink(missing_ok=True)
    assert compile_bytecode()
    for source in sorted(package.rglob("*.py")):
        pyc = Path(importlib.util.cache_from_source(str(source)))
        assert pyc.is_file(), f"no bytecode for {source.name}"
        # the header records the source's modification time: a stale file would be recompiled
        flags, mtime = struct.unpack("<II", pyc.read_bytes()[4:12])
        assert flags == 0 and mtime == int(source.stat().st_mtime) & 0xFFFFFFFF, source.name


# --- the progress bar ---------------------------------------------------------------------------
class _Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_the_rate_counts_from_the_first_report(monkeypatch):
    """The first report comes after work of unknown length (here 5 images): counted over the
    instant since the bar appeared, they made a rate of 125203 image/s. From the first report
    on, 8 more images in 4 s are 2 image/s (counting the first 5 too: 3.25)."""
    clock = _Clock()
    monkeypatch.setattr("tqdm.std.time", clock)  # what each bar takes as its clock
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    bar = _progress.Bar("image", quiet=False)
    bar(5, 20, "img_005.png")
    clock.now += 1e-5
    bar(5, 20, "img_005.png")
    assert bar.bar.format_dict["rate"] is None and "?image/s" in str(bar.bar)  # no rate until time passed
    clock.now += 4.0
    bar(13, 20, "img_013.png")
    shown = str(bar.bar)
    assert "13/20" in shown and "2.00image/s" in shown, shown
    bar.close()


def test_a_quiet_bar_writes_nothing(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    with _progress.Bar("image", quiet=True) as bar:
        bar(1, 3, "a")
        bar(3, 3, "c")
    assert err.getvalue() == ""


# --- the first-run notice ------------------------------------------------------------------------
def test_the_notice_is_said_once_even_under_quiet_and_only_when_kernels_are_missing(monkeypatch, capsys):
    started = []
    monkeypatch.setattr(_progress, "_said", False)
    monkeypatch.setattr(precompile, "start_compiling", lambda names: started.append(list(names)) or True)
    monkeypatch.setattr("stereoseed.threads.CORES", 2)
    monkeypatch.setattr(precompile, "missing_kernels", lambda run: [])
    _progress.say_if_compiling(run="sparse")
    assert capsys.readouterr().err == "" and not started  # a warm cache: nothing said, nothing started
    monkeypatch.setattr(precompile, "missing_kernels", lambda run: ["align", "refine_camera", "mirror_upper"])
    _progress.say_if_compiling(run="sparse")
    _progress.say_if_compiling(run="sparse")  # batch asks again: said once
    err = capsys.readouterr().err.splitlines()
    assert started == [["align", "refine_camera", "mirror_upper"]] * 2
    # (7.7 + 5.9 + 0.1) s of compiling in 2 processes, no less than the longest kernel: about 8 s
    assert err == ["stereoseed: compiling the 3 Numba kernels of this run, once, for the first run on this "
                   "installation: about 8 s on this machine's 2 cores (longer while other programs use them); "
                   "`stereoseed precompile` does it ahead"]


def test_a_first_run_on_an_empty_cache_says_so_first_and_leaves_no_helper_behind(tmp_path):
    """As after a fresh install: the notice comes before any work (here the run is then refused)
    and the helpers compiling the kernels end with the command."""
    command = cli_command("reconstruct", "no_images", "--calib", "calib.json", "--out", "out", "--quiet")
    proc = subprocess.Popen(command, cwd=tmp_path, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")},
                            start_new_session=True)
    _, err = proc.communicate(timeout=60)
    lines = err.splitlines()
    assert proc.returncode == 2, err
    assert lines[0].startswith("stereoseed: compiling the ") and "`stereoseed precompile` does it ahead" in lines[0]
    assert sum("compiling" in line for line in lines) == 1 and lines[-1].startswith("stereoseed: error: ")
    assert wait_until(lambda: not alive_in_group(proc.pid), timeout=10)


# --- the helpers ---------------------------------------------------------------------------------
def test_the_run_takes_what_the_helpers_compiled_instead_of_compiling_it(tmp_path):
    """Three kernels compiled by helper processes into an empty cache: the run's own calls, once
    the helpers are done, load them (a cache hit each, no compile in the run's process), and the
    cache then holds them. (Which process claims a kernel first is a race; the claims are
    tested by the first-run tests.)"""
    names = ["mirror_upper", "largest_angles", "best_of_pairs"]
    out = _python(f"""
        import json
        from stereoseed import precompile as p
        names = {names!r}
        before = p.missing_kernels(names)
        assert p.start_compiling(before, helpers=2)
        import time
        while p._running.busy():  # the helpers first: a run that claims a kernel before them compiles it itself
            time.sleep(0.05)
        for n in names:
            p.kernel(n).compile(p.argument_types(n))
        sig = {{n: p.argument_types(n) for n in names}}
        print(json.dumps({{"before": before, "after": p.missing_kernels(names),
                           "hits": {{n: p.kernel(n)._cache_hits[sig[n]] for n in names}},
                           "misses": {{n: p.kernel(n)._cache_misses[sig[n]] for n in names}}}}))
        p.stop_compiling()
    """, tmp_path, cache=tmp_path / "cache")
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout)
    assert seen["before"] == names and seen["after"] == []
    assert seen["hits"] == dict.fromkeys(names, 1) and seen["misses"] == dict.fromkeys(names, 0)


def test_the_kernel_table_holds_the_types_a_run_passes(tmp_path):
    """The demo on three images (what `stereoseed precompile` runs), its dense stage in its own
    process (one core): the kernels it calls from Python, with the types it passes, are the
    demo's of precompile.RUNS with precompile.KERNELS' types (the dense stage's workers get
    writable copies of arrays the process holds read-only)."""
    out = _python("""
        import json, os
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        from pathlib import Path
        from numba.core import event, types
        from numba.core.dispatcher import Dispatcher
        top = []
        class Calls(event.Listener):
            depth = 0
            def on_start(self, ev):
                Calls.depth += 1
            def on_end(self, ev):
                Calls.depth -= 1
                if Calls.depth == 0:
                    top.append((ev.data["dispatcher"], tuple(ev.data["args"])))
        event.register("numba:compile", Calls())
        from stereoseed.experiments.demo import run_demo
        import sys
        run_demo(Path("out"), n_images=3, dense=True, say=lambda line: None)
        for module in [m for name, m in list(sys.modules.items()) if name.startswith("stereoseed")]:
            for d in list(vars(module).values()):
                if isinstance(d, Dispatcher) and d.py_func.__module__ == module.__name__:
                    top.extend((d, sig) for sig in d._cache_hits)
        seen = {}
        for d, sig in top:
            seen.setdefault(f"{d.py_func.__module__}:{d.py_func.__name__}", set()).add(
                ", ".join(str(t.copy(readonly=False) if isinstance(t, types.Array) else t) for t in sig))
        print(json.dumps({k: sorted(v) for k, v in seen.items()}))
    """, tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout.splitlines()[-1])
    table = {f"{precompile.KERNELS[n][0]}:{precompile.KERNELS[n][1]}": n for n in precompile.RUNS["demo"]}
    # _grid_origin is also called by two other kernels: compiled as part of the first, it is not called alone;
    # _sample_patches only where OpenCV's remap rounds positions (4.x)
    from stereoseed.features import harris

    unseen = {"stereoseed.dense.grid:_grid_origin"} | (
        {"stereoseed.features.harris:_sample_patches"} if harris._remap_is_exact() else set())
    assert set(seen) <= set(table) and set(table) - set(seen) <= unseen
    for key, sigs in seen.items():
        assert sigs == [", ".join(str(t) for t in precompile.argument_types(table[key]))], key


def _njit_functions() -> dict[str, object]:
    from numba.core.dispatcher import Dispatcher

    found = {}
    for info in pkgutil.walk_packages(stereoseed.__path__, "stereoseed."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for value in vars(module).values():
            if isinstance(value, Dispatcher) and value.py_func.__module__ == module.__name__:
                found[f"{module.__name__}.{value.py_func.__qualname__}"] = value
    return found


def test_no_numba_function_takes_its_options_from_whichever_caller_compiles_it_first():
    """Numba gives a function that leaves fastmath or error_model unset the value of the caller
    that compiles it first; called by kernels that differ in it, the function's code, and the
    results of every kernel calling it, would depend on the order kernels are compiled in,
    which helpers compiling beside a run change (and the cache keeps). Functions inlined into
    their callers (inline="always") take each caller's own."""
    functions = _njit_functions()
    callers: dict[str, list[str]] = {name: [] for name in functions}
    for name, d in functions.items():
        scope = d.py_func.__globals__
        for g in d.py_func.__code__.co_names:
            callee = scope.get(g)
            if callee is not None and any(callee is f for f in functions.values()):
                callers[f"{callee.py_func.__module__}.{callee.py_func.__qualname__}"].append(name)
    assert callers["stereoseed.features.image.sample_bilinear"]  # the check sees the calls
    for option, default in (("fastmath", False), ("error_model", "python")):
        values = {}  # the values a function's option can take, followed through the calls to a fixpoint
        changed = True
        while changed:
            changed = False
            for name, d in functions.items():
                own = d.targetoptions.get(option)
                if own is not None:
                    new = {str(own)}
                elif not callers[name]:
                    new = {str(default)}
                else:
                    new = set().union(*(values.get(c, set()) for c in callers[name]))
                if new != values.get(name):
                    values[name], changed = new, True
        torn = {name: sorted(v) for name, v in values.items()
                if len(v) > 1 and functions[name].targetoptions.get("inline", "never") != "always"}
        assert not torn, f"{option} depends on which caller compiles first: {torn}"
