"""The steps of the incremental loop that :func:`stereoseed.pipeline.reconstruct` and the live
run (:mod:`stereoseed.live`) share, so that a live run, which learns its images one at a time,
builds the very model a run on the same images in the same order builds: the world frame moved
next to a far pair, an undecodable image skipped with its reason, one insertion followed by the
release of old views and a checkpoint.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from stereoseed.geometry.projection import camera_center
from stereoseed.io.sequence import ImageSequence
from stereoseed.scene.checkpoint import CheckpointWriter
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.scene.view_store import release_old_views
from stereoseed.sfm.correspondence import CorrespondenceSource
from stereoseed.sfm.mapper import insert_view
from stereoseed.sfm.options import MapperOptions
from stereoseed.sfm.registration.base import FailureKind

__all__ = ["RECENTRE_ABOVE_BASELINES", "frame_offset", "shift", "unreadable_report", "insert_next"]

log = logging.getLogger(__name__)

# The world frame is moved next to the cameras when the pair's centre lies farther from its origin
# than this many baselines: at 1e4 baselines float64 still resolves a micron of a metre-sized
# scene; at 1e7 (UTM coordinates) the BA moved cameras by 1-2 cm.
RECENTRE_ABOVE_BASELINES = 1e3


def frame_offset(P_pair: list[np.ndarray]) -> np.ndarray | None:
    """The point (3,) the run's frame is moved to (the middle of the pair's centres, rounded to a
    whole baseline), or None when the world frame is near enough."""
    c0, c1 = (camera_center(np.asarray(P, np.float64)) for P in P_pair)
    baseline = float(np.linalg.norm(c1 - c0))
    middle = 0.5 * (c0 + c1)
    if not (np.all(np.isfinite(middle)) and baseline > 0) or np.linalg.norm(middle) <= RECENTRE_ABOVE_BASELINES * baseline:
        return None
    return np.round(middle / baseline) * baseline


def shift(offset: np.ndarray) -> np.ndarray:
    """(4, 4): homogeneous world point X_local to X_local + offset, so P @ shift(o) sees X - o."""
    T = np.eye(4)
    T[:3, 3] = offset
    return T


def unreadable_report(recon: Reconstruction, images: Sequence[np.ndarray], k: int) -> dict[str, Any] | None:
    """The report of image k skipped because its file cannot be decoded (as the mapper skips an
    image of another size: reported with the reason, the run goes on), or None."""
    reason = images.unreadable(k) if isinstance(images, ImageSequence) else None
    if reason is None:
        return None
    log.info("%s", reason)
    report = {"image": recon.views[k].name, "status": "failed", "reason": reason, "failure": FailureKind.UNREADABLE}
    recon.fail(k, reason, report)
    return report


def insert_next(recon: Reconstruction, images: Sequence[np.ndarray], k: int, options: MapperOptions,
                source: CorrespondenceSource, spill: Path, saver: CheckpointWriter) -> dict[str, Any]:
    """Image k into the model (skipped with its reason when it cannot be decoded), the views out
    of the working set spilled to ``spill``, the checkpoint saved: image k's report."""
    report = unreadable_report(recon, images, k) or insert_view(recon, k, options, source)
    release_old_views(recon, options, spill)
    saver.save(recon)
    return report
