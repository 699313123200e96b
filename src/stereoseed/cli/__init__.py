"""Command-line interface: each subcommand is a few lines over the Python API (the commands'
modules: :mod:`.calibration`, :mod:`.reconstruct`, :mod:`.results`, :mod:`.tools`).

Errors the user can fix (bad input, degenerate data) are :class:`StereoseedError`: printed as
one line ``stereoseed: error: ...`` with exit code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import sys
import textwrap
import warnings

# One BLAS thread unless the user says otherwise, set before NumPy loads OpenBLAS: the pipeline's
# linear algebra is small matrices, where OpenBLAS's extra threads only spin against the
# feature thread and the dense workers (docs/scaling.md).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _keep_large_arrays_mapped() -> None:
    """glibc raises its mmap threshold to the largest block freed (up to 32 MB): after that the
    dense stage's arrays of a few to 32 MB come from the heap, and once freed they stay resident
    between live ones. At 3072 x 2048 the full run's peak memory was 0.5 GB higher (docs/dense.md).
    A fixed threshold keeps them mapped, so that freeing one gives its memory back. Set for this
    process (mallopt) and, through the environment, for the pair workers it starts."""
    if "malloc" in os.environ.get("GLIBC_TUNABLES", ""):  # the user's own tuning, which glibc has read
        return
    # a 4 MB array's pages cost ~0.2 ms to map: nothing next to its use
    settings = [(name, option, value) for name, option, value in
                (("MALLOC_MMAP_THRESHOLD_", -3, 4 << 20), ("MALLOC_TRIM_THRESHOLD_", -1, 16 << 20))
                if name not in os.environ]  # (-3, -1: glibc's M_MMAP_THRESHOLD, M_TRIM_THRESHOLD)
    for name, _, value in settings:
        os.environ[name] = str(value)
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        for _, option, value in settings:
            libc.mallopt(option, value)
    except (OSError, AttributeError):  # not glibc: its allocator does as it does
        pass


_keep_large_arrays_mapped()

# the commands' modules import NumPy: after the BLAS setting
from stereoseed.cli import calibration, data, live, mesh, reconstruct, results, tools  # noqa: E402
from stereoseed.cli._terminal import LibraryLines, complain, on_main_thread, warn  # noqa: E402
from stereoseed.errors import StereoseedError  # noqa: E402


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("stereoseed")
    except PackageNotFoundError:
        return "unknown (not installed)"


DESCRIPTION = ("A metric 3D model (cameras, sparse points, a quasi-dense cloud) from an ordered image sequence "
               "whose first two images were taken by a calibrated stereo pair.")

# the workflow: (command, what it does); the steps after a run are left out where their command
# is not registered (an optional module)
WORKFLOW = [
    ("stereoseed target --out target/", "print a calibration target (or describe your own: examples/)"),
    ("stereoseed calibrate --target target/target.json PAIR1.png PAIR2.png \\\n"
     "         --lens-images1 ... --lens-images2 ... -o calib.json", "the pair's two cameras from photos of the target"),
    ("stereoseed reconstruct IMAGES --calib calib.json --out result/ [--dense] [--config run.toml]",
     "IMAGES: a folder or list file, the pair's two photos first, then the walk"),
]
AFTER = [
    ("stereoseed view result/", "report.html in the browser"),
    ("stereoseed export result/ --format colmap --out model/", "for COLMAP, OpenMVS, splatting trainers"),
    ("stereoseed mesh result/", "a surface mesh of the quasi-dense cloud"),
]


def _epilog(commands: set[str]) -> str:
    lines = ["workflow:"]
    for n, (cmd, what) in enumerate(WORKFLOW, 1):
        lines += [f"  {n}. {cmd}", f"       {what}"]
    after = [(cmd, what) for cmd, what in AFTER if cmd.split()[1] in commands]
    lines += [f"  {len(WORKFLOW) + 1}. then:"] + [f"       {cmd}   ({what})" for cmd, what in after]
    lines += ["", "Try it on a synthetic scene: stereoseed demo. Every option: stereoseed COMMAND --help.",
              "From Python: stereoseed.calibrate, stereoseed.reconstruct, stereoseed.load_result (README)."]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stereoseed", description=textwrap.fill(DESCRIPTION, 90),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for commands in (calibration, reconstruct, live, results, tools, mesh, data):
        commands.register(sub)
    parser.epilog = _epilog(set(sub.choices))
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line for a user, not a source excerpt."""
    warn(str(message))

def _configure_logging(args: argparse.Namespace) -> None:
    """The library logs; the terminal shows warnings, or every step with --verbose, or errors
    only with --quiet."""
    level = (logging.DEBUG if getattr(args, "verbose", False) else
             logging.ERROR if getattr(args, "quiet", False) else logging.WARNING)
    logger = logging.getLogger("stereoseed")
    logger.setLevel(level)
    for old in [h for h in logger.handlers if getattr(h, "_stereoseed", False)]:
        logger.removeHandler(old)  # main() may run several times in one process (tests, notebooks)
    handler = LibraryLines(logging.DEBUG)  # on a line of its own beside a progress bar
    handler._stereoseed = True
    logger.addHandler(handler)

def _interrupt(signum, frame) -> None:
    """SIGTERM ends a run as Ctrl-C does: what is written stays consistent, --resume continues."""
    raise KeyboardInterrupt

def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args)
    shown_before, warnings.showwarning = warnings.showwarning, _show_warning
    term_before = signal.signal(signal.SIGTERM, _interrupt) if on_main_thread() else None
    try:
        return int(args.func(args) or 0)
    except StereoseedError as e:
        complain(f"stereoseed: error: {e}")
        return 2
    except KeyboardInterrupt:
        hint = "; run the same command with --resume to continue" if args.command in ("reconstruct", "live") else ""
        complain(f"stereoseed: interrupted{hint}")
        return 130
    except OSError as e:  # e.g. an output folder that cannot be created
        complain(f"stereoseed: error: {e.filename or ''}: {e.strerror or e}")
        return 2
    finally:
        warnings.showwarning = shown_before  # main() is also called in-process (tests, notebooks)
        if term_before is not None:
            signal.signal(signal.SIGTERM, term_before)

def run() -> None:
    """The ``stereoseed`` command: :func:`main`, then exit. The garbage collector is frozen
    first: the interpreter's teardown frees module after module, and each collection it triggers
    would walk Numba's object graph again (0.6-0.7 s of a 5 s run on the 14-image box, after the
    last output was written). Not in :func:`main`, which tests and notebooks call in-process."""
    code = main()
    gc.freeze()
    sys.exit(code)
