"""What a run shows on the terminal while it works: its progress bars and the first-run notice."""
from __future__ import annotations

import sys

from stereoseed.cli._terminal import complain


class Bar:
    """The progress callback (done, total, message) as a tqdm bar on stderr, shown from the
    first report on: a run refused before any work leaves only its error line. ``after``: the
    bar of the stage before, closed (its time stopped) when this one starts.

    The rate counts from the first report: the items done before it (often all the work of the
    first one, or more) took an unknown time, and counted over the instant since the bar
    appeared they made a rate of a hundred thousand images a second. Until a second report has
    come there is no rate to show (tqdm's "?")."""

    def __init__(self, unit: str, quiet: bool, after: "Bar | None" = None):
        self.unit, self.quiet, self.after, self.bar = unit, quiet, after, None

    def __call__(self, done: int, total: int, message: str) -> None:
        from tqdm import tqdm

        if self.bar is None:
            if self.after is not None:
                self.after.close()
            # initial: tqdm's rate is (n - initial) / the time since the bar started
            self.bar = tqdm(total=total, initial=done, unit=self.unit, file=sys.stderr, disable=self.quiet)
        self.bar.total, self.bar.n = total, done
        self.bar.set_postfix_str(message[:40])

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "Bar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_said = False  # the notice is said once a process (batch and in-process callers run several times)


def compiling_notice(seconds: float, cores: int, kernels: int) -> str:
    """The first-run notice: what happens, about how long, and how to have it done ahead."""
    return (f"stereoseed: compiling the {kernels} Numba kernels of this run, once, for the first run on this "
            f"installation: about {seconds:.0f} s on this machine's {cores} core{'s' if cores != 1 else ''} "
            f"(longer while other programs use them); `stereoseed precompile` does it ahead")


def say_if_compiling(run: str = "dense") -> None:
    """Before a run whose kernels (:data:`stereoseed.precompile.RUNS` ``[run]``: "sparse",
    "dense", "demo-sparse" or "demo") are not all in Numba's cache (a first run on this installation): start
    compiling them in helper processes beside the run, and say so once on stderr with about how
    long it takes, also under ``--quiet``: the run is that much slower, which is not progress
    but something to know."""
    global _said
    from stereoseed import precompile
    from stereoseed.threads import CORES

    missing = precompile.missing_kernels(run)
    if not missing:
        return
    processes = min(CORES, len(missing)) if precompile.start_compiling(missing) else 1
    if not _said:
        _said = True
        complain(compiling_notice(precompile.estimated_seconds(missing, processes), CORES, len(missing)))
