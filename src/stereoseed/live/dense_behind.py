"""The dense stage behind the walk (``stereoseed live --dense``): the propagation of each pair of
the walk, the dense stage's costly part, run in a worker process beside the live run once both
its views are out of the window's reach (the window's bundle adjustment no longer moves them), so
that stopping leaves only the triangulation and the fusion to do.

A pair's matches depend on its cameras through the epipolar constraint of the propagation: found
with the cameras of then, they are triangulated with the final cameras when the run stops
(:func:`stereoseed.dense.densify.densify`'s ``propagated``), so the cloud stands where the final
cameras put it; the final adjustment moves the cameras by a fraction of the propagation's
epipolar band, so the matches are those the final cameras would give but for the few at its
edge. The matches wait on disk, in the staging folder (one .npy file a pair): the run's memory
stays flat however long the walk. A pair whose views the end of the run pairs otherwise (a view
flagged by the final judgement leaves the dense stage) is propagated then, as ``reconstruct
--dense`` does.
"""
from __future__ import annotations

import logging
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.cluster import ProcessesBeside
from stereoseed.config import Config
from stereoseed.dense.densify import PairJob, dense_pairs, pair_job, propagate_pair
from stereoseed.dense.frames import dense_frames
from stereoseed.io.atomic import atomic_path
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.threads import CORES

__all__ = ["DenseBehind", "FOLDER"]

log = logging.getLogger(__name__)

FOLDER = ".dense-behind"  # in the staging folder: the pairs' matches, dropped when the result is written


def _propagated(job: PairJob) -> tuple[np.ndarray, dict[str, Any]]:
    return propagate_pair(*job.propagation_args)


# pairs sent to the worker at most at a time: each holds its two images in this process until it
# runs (37 MB at 6 megapixels), so a walk faster than the propagation must not queue them all; a
# pair left unsent is propagated at the stop, as reconstruct --dense does
IN_FLIGHT = 2


class DenseBehind:
    """Pairs propagated in one worker process while the run goes on (the run keeps the other
    core). :meth:`after_insertion` after each insertion; :meth:`finish` when the run stops gives
    :func:`~stereoseed.dense.densify.densify` its ``propagated``; :meth:`close` in any case.
    Not for a run whose every insertion moves every camera (``PipelineConfig.ba = "global"``):
    :meth:`for_run` gives None there."""

    @classmethod
    def for_run(cls, staging: Path, cfg: Config) -> "DenseBehind | None":
        cfg = cfg.resolve()  # (the mode's window and BA policy)
        return None if cfg.pipeline.ba == "global" else cls(staging, cfg)

    def __init__(self, staging: Path, cfg: Config):
        self.cfg = cfg
        self.folder = Path(staging) / FOLDER
        self.folder.mkdir(mode=0o700, exist_ok=True)
        # one worker, a core left to the insertions (the page's latency is theirs)
        self._workers = ProcessesBeside(1, cores_each=max(1, CORES - 1))
        self._pool = self._workers.pool
        self._running: dict[tuple[int, int], Future] = {}
        self.done: dict[tuple[int, int], tuple[Path, dict[str, Any]]] = {}
        self._sent: set[tuple[int, int]] = set()

    def after_insertion(self, recon: Reconstruction) -> None:
        """Send the pairs whose views the window's adjustment no longer moves (the last
        ``PipelineConfig.window`` registered views may still move; on a rig walk the window
        counts stations, two views each), at most :data:`IN_FLIGHT` at a time, and keep what came
        back. A failure here is said and leaves the pairs to the stop: the walk goes on."""
        try:
            self._collect(wait=False)
            if len(self._running) >= IN_FLIGHT:
                return
            window = self.cfg.pipeline.window * (2 if recon.rig is not None else 1)
            moving = set(recon.registered_views[-window:])
            pairs = [p for p in dense_pairs(recon, self.cfg) if p not in self._sent and not moving & set(p)]
            pairs = pairs[:max(IN_FLIGHT - len(self._running), 0)]
            if not pairs:
                return
            frames = dense_frames(recon.views, self.cfg.dense.resolution)
            for pair in pairs:
                self._sent.add(pair)
                self._running[pair] = self._pool.submit(_propagated, pair_job(recon, pair, self.cfg, frames))
        except Exception as e:  # noqa: BLE001 - the dense stage behind is a saving, never the walk's end
            log.warning("dense stage behind the walk: %s; its pairs are propagated when the run stops", e)

    def _collect(self, wait: bool) -> None:
        for pair, future in list(self._running.items()):
            if not (wait or future.done()):
                continue
            del self._running[pair]
            try:
                matches, report = future.result()
            except Exception as e:  # noqa: BLE001 - a pair that failed behind is propagated at the end
                log.info("dense stage behind the walk: pair %s: %s; propagated at the end", pair, e)
                continue
            path = self.folder / f"{pair[0]}_{pair[1]}.npy"
            with atomic_path(path) as tmp:
                with open(tmp, "wb") as fh:
                    np.save(fh, matches, allow_pickle=False)
            self.done[pair] = (path, report)

    def finish(self) -> dict[tuple[int, int], tuple[Path, dict[str, Any]]]:
        """Every pair sent, once it has come back: {pair: (its matches' file, its report)}."""
        self._collect(wait=True)
        return dict(self.done)

    def close(self, abandon: bool = False) -> None:
        """Stop the worker: once idle, or at once (``abandon``: the run was interrupted, the
        pairs under way are not wanted)."""
        self._workers.close(abandon)
