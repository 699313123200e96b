"""What a run shows on the terminal while it works: its progress bars and the first-run notice."""
from __future__ import annotations

import sys

from stereoseed.cli._terminal import complain


class Bar:
    """The progress callback (done, total, message) as a tqdm bar on stderr, shown from the
    first report on: a run refused before any work leaves only its error line. ``after``: the
    bar of the stage before, closed (its time stopped) when this one starts."""

    def __init__(self, unit: str, quiet: bool, after: "Bar | None" = None):
        self.unit, self.quiet, self.after, self.bar = unit, quiet, after, None

    def __call__(self, done: int, total: int, message: str) -> None:
        from tqdm import tqdm

        if self.bar is None:
            if self.after is not None:
                self.after.close()
            self.bar = tqdm(total=total, unit=self.unit, file=sys.stderr, disable=self.quiet)
        self.bar.total, self.bar.n = total, done
        self.bar.set_postfix_str(message[:40])

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "Bar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

def say_if_compiling(quiet: bool) -> None:
    """One line before a first run on this installation: it compiles the kernels first."""
    from stereoseed.precompile import kernels_cached

    if not quiet and kernels_cached() is False:
        complain("stereoseed: first run on this installation: compiling the Numba kernels once (about a minute on "
              "two cores; `stereoseed precompile` does it ahead)")
