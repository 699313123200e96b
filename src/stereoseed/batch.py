"""``stereoseed batch``: many sequences, one result folder each, one job per sequence (locally
one after the other, or on a Dask cluster's workers: :mod:`stereoseed.cluster`).

The list of sequences (docs/formats.md) has one line per sequence, ``IMAGES CALIB OUT``,
whitespace-separated (quote a path holding spaces), ``#`` starting a comment. IMAGES and CALIB
are what ``stereoseed reconstruct`` takes; relative paths are resolved against the list file's
folder, a relative OUT against ``out_root`` (default: that folder too), inside which every OUT
must lie unless the caller allows otherwise. A job gets paths, not
images: a worker reads its sequence itself, so every worker must see the same paths.

A sequence that fails (a missing file, a bad calibration, any exception) is reported with a
one-line reason; the others still run. Each result folder is written as a whole
(:class:`stereoseed.output.result_set.ResultSet`), as ``stereoseed reconstruct`` writes it.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stereoseed.cluster import JobPool
from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.pipeline import Progress, reconstruct_to_folder

__all__ = ["Sequence", "Outcome", "read_sequence_list", "run_sequence", "run_batch", "failure_reason"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sequence:
    """One line of the list: ``name`` (OUT as written, for messages), absolute paths, and the
    line number."""

    name: str
    images: str
    calib: str
    out: str
    line: int


@dataclass(frozen=True)
class Outcome:
    """A sequence's end: ``summary`` (registered, images, points, skipped, dense_points when
    the dense stage ran, seconds) when it was reconstructed, else the one-line ``reason``."""

    sequence: Sequence
    summary: dict[str, Any] | None = None
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.summary is not None


def read_sequence_list(path: str | Path, out_root: str | Path | None = None,
                       allow_outside: bool = False) -> list[Sequence]:
    """The sequences of a list file, in file order. Raises :class:`StereoseedError` naming the
    file and line for a line without three fields; for two lines writing the same folder, or
    one inside the other (however written: ``x/../res`` is ``res``, links followed); and,
    unless ``allow_outside``, for an OUT that is not inside ``out_root`` (an absolute path, or
    one climbing out with ``..``). Whether each sequence's files exist is its job's business
    (a missing one fails that sequence only)."""
    path = Path(path)
    if not path.is_file():
        raise StereoseedError(f"{path}: sequence list not found; give a text file with one 'IMAGES CALIB OUT' "
                              f"line per sequence")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise StereoseedError(f"{path}: cannot be read as UTF-8 text ({e}); give a text sequence list") from None
    base = path.resolve().parent
    root = Path(os.path.realpath(base if out_root is None else out_root))
    sequences: list[Sequence] = []
    seen: dict[Path, int] = {}
    for number, line in enumerate(text.splitlines(), 1):
        if "\0" in line:  # no path holds one (the OS refuses it): a binary file, or a damaged list
            raise StereoseedError(f"{path}, line {number}: a NUL byte, which no path can hold; give a text sequence "
                                  f"list")
        try:
            fields = shlex.split(line, comments=True)
        except ValueError as e:  # an unclosed quote
            raise StereoseedError(f"{path}, line {number}: {e}; quote a path holding spaces, \"like this\"") from None
        if not fields:
            continue
        if len(fields) != 3:
            raise StereoseedError(f"{path}, line {number}: {len(fields)} field(s); give IMAGES CALIB OUT "
                                  f"(quote a path holding spaces)")
        images, calib, out = fields
        resolved = Path(os.path.realpath(root / out))  # one folder, however the line names it
        if not allow_outside and root not in resolved.parents:
            raise StereoseedError(f"{path}, line {number}: OUT {out} lies outside the output root {root}; give a "
                                  f"relative path below it, or --allow-outside")
        for other, first in seen.items():
            if other == resolved or other in resolved.parents or resolved in other.parents:
                what = "both write" if other == resolved else "write one inside the other:"
                raise StereoseedError(f"{path}, lines {first} and {number}: {what} {out}; give each sequence a folder "
                                      f"of its own")
        seen[resolved] = number
        sequences.append(Sequence(out, str(base / images), str(base / calib), str(resolved), number))
    if not sequences:
        raise StereoseedError(f"{path}: no sequence; give one 'IMAGES CALIB OUT' line per sequence")
    return sequences


def run_sequence(job: tuple[Sequence, Config, bool]) -> dict[str, Any]:
    """One batch job: reconstruct ``(sequence, cfg, dense)`` into its result folder, as
    ``stereoseed reconstruct`` does. Returns a small summary (it may travel back over the
    network; the report itself is in the folder)."""
    sequence, cfg, dense = job
    report = reconstruct_to_folder(sequence.images, sequence.calib, sequence.out, cfg, dense=dense)
    summary = {"registered": report["registered"], "images": report["images"], "points": report["points"],
               "skipped": sum(r.get("status") == "failed" for r in report["per_image"]),
               "seconds": report["seconds"]}
    if "dense" in report:
        summary["dense_points"] = report["dense"]["points"]
    return summary


def failure_reason(error: BaseException) -> str:
    """One line saying why a job failed: our messages as they are, a file error with its file,
    anything else with its type (a bug, or a worker lost)."""
    if isinstance(error, StereoseedError):
        text = str(error)
    elif isinstance(error, OSError) and error.strerror:
        text = f"{error.filename or ''}: {error.strerror}" if error.filename else error.strerror
    else:
        text = f"{type(error).__name__}: {error}"
    lines = text.strip().splitlines()
    return lines[0] if lines else type(error).__name__


def run_batch(sequences: list[Sequence], cfg: Config = Config(), dense: bool = False, pool: JobPool | None = None,
              progress: Progress | None = None) -> list[Outcome]:
    """Reconstruct every sequence (a job each on ``pool``; default one after the other in this
    process). Returns the outcomes in list order; a failed sequence does not stop the others.

    On a Dask cluster a sequence's dense stage runs its pairs one after the other in its worker
    (a worker process cannot start a pool of its own; the cluster's parallelism is the
    sequences); the cloud is the same as a local run's."""
    pool = pool or JobPool()
    if pool.remote:
        cfg = dataclasses.replace(cfg, dense=dataclasses.replace(cfg.dense, workers=1))
    outcomes: list[Outcome] = []
    if progress:
        progress(0, len(sequences), f"running {pool.where}")
    jobs = ((s, cfg, dense) for s in sequences)
    for sequence, done in zip(sequences, pool.in_order(run_sequence, jobs)):
        try:
            outcome = Outcome(sequence, summary=done.result())
        except Exception as e:  # this sequence only: the others go on
            outcome = Outcome(sequence, reason=failure_reason(e))
            log.info("%s: failed: %s", sequence.name, outcome.reason)
        outcomes.append(outcome)
        if progress:
            progress(len(outcomes), len(sequences), f"{sequence.name}: {'done' if outcome.ok else 'failed'}")
    return outcomes
