"""A live run: photos inserted one at a time as they arrive, the result folder written as
``reconstruct`` writes it when the run stops.

Each photo is copied into the staging folder's ``images/`` (the run reads only its own copies:
a photo deleted or rewritten in the watched folder afterwards changes nothing) and inserted at
once by the steps ``reconstruct`` runs (:mod:`stereoseed.sfm.steps`): the pair's
:func:`~stereoseed.sfm.mapper.initialise`, then per image the registration, the window's
bundle adjustment and the flags, a checkpoint after each. Stopping (:meth:`LiveRun.finish`)
signs that checkpoint for the images as they came and has :func:`stereoseed.pipeline.reconstruct`
resume from it: the finishing step and the result folder are ``reconstruct``'s own, on the same
images in the same order, so the result is the one ``stereoseed reconstruct`` gives on
``images/`` listed in that order (inputs.json lists them). An interrupted live run resumes from
its checkpoint and its list of arrivals (``--resume``).

A stereo rig walked with both cameras (``rig``): the photos come a station at a time, left then
right (:class:`stereoseed.live.watch.RigWatch` pairs them), and are placed as ``reconstruct
--rig`` places them, the calibrated pair the first station.
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.io.atomic import atomic_path, write_json
from stereoseed.io.files import read_calibration_unit
from stereoseed.io.sequence import ImageSequence
from stereoseed.live.dense_behind import FOLDER as DENSE_BEHIND, DenseBehind
from stereoseed.live.watch import Arrival
from stereoseed.output.inputs import write_inputs
from stereoseed.output.result_set import ResultSet
from stereoseed.pipeline import CHECKPOINT, load_sequence_and_lenses, reconstruct, save_outputs
from stereoseed.scene.checkpoint import (SPILL_SUFFIX, CheckpointWriter, checkpoint_header, inputs_key,
                                         load_checkpoint, save_checkpoint, spill_folder)
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.scene.view_store import view_of_input, working_set
from stereoseed.sfm.correspondence import HarrisZncc
from stereoseed.sfm.mapper import initialise, pair_rig
from stereoseed.sfm.steps import frame_offset, insert_next, shift

__all__ = ["LiveRun", "IMAGES", "ARRIVALS"]

log = logging.getLogger(__name__)

IMAGES = "images"  # the run's copies of the photos, kept with the result (inputs.json names them)
ARRIVALS = ".live-arrivals.json"  # the photos' names in the order they came: what --resume reads
_LIVE_KEY = "+live"  # a live checkpoint's key: the pair's inputs and the settings, then this


class LiveRun:
    """A live run writing the result folder ``out`` (held, one run at a time, from the start).
    :meth:`add` each photo as it comes, then :meth:`finish` (or :meth:`close` to leave the
    staging folder for ``resume``). ``resume``: continue an interrupted live run on ``out``.
    ``rig``: the photos are a stereo rig's stations, left and right interleaved (:meth:`add`
    takes a station's two together). ``dense``: the dense stage's propagation runs behind the
    walk (:class:`~stereoseed.live.dense_behind.DenseBehind`), for :meth:`finish` with ``dense``."""

    def __init__(self, calib: str | Path, out: str | Path, cfg: Config = Config(), resume: bool = False,
                 rig: bool = False, dense: bool = False):
        self.t0 = time.perf_counter()
        self.calib = str(calib)
        self.out = Path(out)
        self.rig = rig
        self.cfg = cfg.resolve()
        self.options = self.cfg.mapper_options()  # each insertion's components get their sections from it
        self.unit = read_calibration_unit(self.calib)  # a calibration that cannot be read: refused now
        self.results = ResultSet(out).lock()
        try:
            self.results.check()
            keep = (CHECKPOINT, CHECKPOINT + SPILL_SUFFIX, IMAGES, ARRIVALS) if resume else ()
            self.staging = self.results.open(keep=keep)
            self.images_dir = self.staging / IMAGES
            self.images_dir.mkdir(mode=0o700, exist_ok=True)
        except BaseException:
            self.results.unlock()
            raise
        self.checkpoint = self.staging / CHECKPOINT
        self.spill = spill_folder(self.checkpoint)
        self.names: list[str] = []
        self.arrived: list[float] = []  # when each photo settled (monotonic s; NaN: before a resume)
        self.seq: ImageSequence | None = None
        self.lenses: list | None = None
        self.P_pair: list[np.ndarray] | None = None
        self.offset: np.ndarray | None = None
        self.recon: Reconstruction | None = None
        self.source = HarrisZncc.of(self.cfg)
        self.key = ""
        self.saver = CheckpointWriter(self.checkpoint, self.key)  # its key set with the pair
        self.resumed: list[str] = []
        self.dense_behind: DenseBehind | None = None
        try:
            if resume:
                self._resume()
            if dense:  # after the resume, which inserts again what the checkpoint did not hold
                self.dense_behind = DenseBehind.for_run(self.staging, self.cfg)
                if self.dense_behind is not None and self.recon is not None:
                    self.dense_behind.after_insertion(self.recon)
        except BaseException:  # refused (another kind of run, photos gone): the folder is free again
            self._close_dense_behind(abandon=True)
            self.results.unlock()
            raise

    # ------------------------------------------------------------------ arrivals
    def add(self, *arrivals: Arrival) -> dict[str, Any] | None:
        """Take complete photos (one; on a rig walk a station's two, left then right): copied into
        ``images/``, then inserted (the first two: the calibrated pair, set up once the second
        comes). Returns the last one's report (None for the first photo alone)."""
        if self.rig and len(arrivals) != 2:
            raise ValueError("a rig walk takes a station's two photos together")
        for arrival in arrivals:
            with atomic_path(self.images_dir / arrival.name) as tmp:
                tmp.write_bytes(arrival.data)
            self.names.append(arrival.name)
            self.arrived.append(arrival.settled_at)
        write_json(self.staging / ARRIVALS, {"images": self.names, "rig": self.rig})
        return self._insert_taken()

    def _insert_taken(self) -> dict[str, Any] | None:
        """Insert the photos taken and not yet in the model."""
        report = None
        if self.recon is None and len(self.names) >= 2:
            report = self._pair()
        if self.recon is not None:
            for k in range(len(self.recon.views), len(self.names)):
                # a station's both views first: its left image is placed with its right
                self.seq.append(self.images_dir / self.names[k])
                self.recon.add_view(view_of_input(self.names[k], self.seq, k))
            # from the first view not reached: a rig run stopped between a station's two
            # insertions resumes with its right image, already a view of the checkpoint
            for k in range(len(self.recon.reports()), len(self.names)):
                report = insert_next(self.recon, self.seq, k, self.options, self.source, self.spill, self.saver)
                log.info("%s: %s", self.names[k], report["status"])
            if self.dense_behind is not None:
                self.dense_behind.after_insertion(self.recon)
        return report

    def _sequence(self) -> None:
        """The pair's sequence, calibration and lenses, as ``reconstruct`` loads them."""
        pair = [str(self.images_dir / n) for n in self.names[:2]]
        self.seq, _, self.P_pair, self.lenses = load_sequence_and_lenses(pair[:1] if self.rig else pair, self.calib,
                                                                         self.cfg.video, ordering=None,
                                                                         rig_right=pair[1:] if self.rig else None)
        self.key = inputs_key(self.seq, self.names[:2], self.P_pair, self.cfg, self.rig) + _LIVE_KEY
        self.offset = frame_offset(self.P_pair)
        self.spill.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.saver.key = self.key

    def _local_pair(self) -> list[np.ndarray]:
        if self.offset is None:
            return self.P_pair
        return [np.asarray(P, np.float64) @ shift(self.offset) for P in self.P_pair]

    def _pair(self) -> dict[str, Any]:
        """The calibrated pair: initialised as ``reconstruct`` does."""
        self._sequence()
        self.recon, report = initialise(self.seq, self.names[:2], self._local_pair(), self.cfg, self.source,
                                        rig=self.rig)
        self.saver.save(self.recon)
        return report

    # ------------------------------------------------------------------ resuming
    def _resume(self) -> None:
        try:
            arrivals = json.loads((self.staging / ARRIVALS).read_text(encoding="utf-8"))
            names, rig = arrivals["images"], bool(arrivals.get("rig", False))
            if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
                raise ValueError("not a list of names")
        except FileNotFoundError:
            log.info("%s: no live run to resume; starting", self.results.shown)
            return
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise StereoseedError(f"{self.staging / ARRIVALS}: unreadable ({e}); run without --resume to start "
                                  f"again") from None
        if rig != self.rig:
            raise StereoseedError(f"{self.results.shown}: the interrupted run was "
                                  f"{'a rig walk (--rig)' if rig else 'one camera (no --rig)'}; resume it as it was")
        kept = [n for n in names if (self.images_dir / n).is_file()]
        if kept != names:
            raise StereoseedError(f"{self.images_dir}: the run's copies of {len(names) - len(kept)} photo(s) are "
                                  f"gone; run without --resume to start again")
        self.names = list(names)
        self.arrived = [float("nan")] * len(names)
        if len(names) < 2:
            return
        self._sequence()
        count, key = self._checkpoint_meta()
        if count is not None:
            for n in names[2:count]:  # the views of the checkpoint read their images from here
                self.seq.append(self.images_dir / n)
            if key != self.key:  # stopped while finishing: signed for reconstruct, these photos
                key = inputs_key(self.seq, self.names[:count], self.P_pair, self.cfg, self.rig)
            state = load_checkpoint(self.checkpoint, self.seq, self.names[:count], key)
            if state is not None:
                self.recon = state[0]
                self.recon.rig = pair_rig(self._local_pair(), self.rig)  # held by the run, not the checkpoint
                for i in working_set(self.recon, self.cfg):  # the next insertions read their grey images
                    self.recon.views[i].restore_gray()
                self.resumed = [v.name for v in self.recon.views]
                log.info("resuming after %s (%d photos done)", self.resumed[-1], len(self.resumed))
            else:
                self._sequence()  # the pair's again: every photo is inserted again
        self._insert_taken()

    def _checkpoint_meta(self) -> tuple[int | None, str]:
        """(how many views, which key) the interrupted run's checkpoint says it holds: signed by
        the live key, or, when the run was stopped while finishing, by ``reconstruct``'s for all
        its photos (:func:`load_checkpoint` then checks the signature); (None, "") without one."""
        header = checkpoint_header(self.checkpoint)
        if header is None:
            return None, ""
        count, key = header
        if not 2 <= count <= len(self.names):
            log.warning("%s: its views are not the photos taken; inserting them again", self.checkpoint)
            return None, ""
        return count, key

    # ------------------------------------------------------------------ stopping
    def finish(self, dense: bool = False) -> dict[str, Any]:
        """Stop: the run's last checkpoint signed for ``reconstruct`` on the photos taken, in
        their order, which resumes from it (its finishing step), then (``dense``) its dense
        stage, and the result folder written as ``reconstruct`` writes it and swapped in whole.
        Returns the report. Interrupted, the staging folder keeps everything for ``resume``."""
        try:
            self.saver.__exit__(None, None, None)  # the last checkpoint written
            if self.recon is None:
                raise StereoseedError(f"{self.results.shown}: {len(self.names)} photo(s) arrived; the calibrated "
                                      f"pair needs two (what came is kept for --resume)")
            live_s = time.perf_counter() - self.t0
            # reconstruct's key for these inputs: its resume takes this model as its own
            save_checkpoint(self.checkpoint, self.recon, inputs_key(self.seq, self.names, self.P_pair, self.cfg,
                                                                    self.rig))
            self.recon = None  # the model is read back from the checkpoint: not held twice
            recon, report = reconstruct(self.seq, self.names, self.P_pair, self.cfg, checkpoint=self.checkpoint,
                                        resume=True, rig=self.rig)
            report.pop("resumed_images", None)  # this run inserted them; a resumed live run says so below
            report["live"] = {"photos": len(self.names), "resumed_photos": self.resumed}
            cloud = None
            if dense:  # on the final cameras, as reconstruct --dense: its pairs on local processes
                from stereoseed.dense.densify import densify

                # the pairs propagated behind the walk are only triangulated, with the final cameras
                found = self.dense_behind.finish() if self.dense_behind is not None else {}
                self._close_dense_behind()
                cloud, report["dense"] = densify(recon, self.cfg, self.staging, propagated=found)
            report.update(unit=self.unit, timing={"total_s": time.perf_counter() - self.t0,
                                                  "stages_s": {"live": live_s,
                                                               "finishing": time.perf_counter() - self.t0 - live_s}})
            save_outputs(recon, report, self.staging, self.cfg, self.lenses, cloud)
            write_inputs(self.staging, self.out, [self.seq.source(i) for i in range(len(self.seq))], self.names,
                         self.rig)
            self.results.commit(drop=(".checkpoint*", ARRIVALS, DENSE_BEHIND))
            return report
        finally:
            self._close_dense_behind(abandon=True)
            self.results.unlock()

    def _close_dense_behind(self, abandon: bool = False) -> None:
        if self.dense_behind is not None:
            self.dense_behind.close(abandon)
            self.dense_behind = None

    def close(self) -> None:
        """Leave without finishing: the staging folder keeps the checkpoint, the photos and their
        order for ``resume`` (a run that took no photo leaves nothing behind)."""
        try:
            self._close_dense_behind(abandon=True)
            self.saver.__exit__(None, None, None)
            if not self.names:
                self.results.abandon()
        finally:
            self.results.unlock()
