"""The end of the run (after the last insertion): the mode's finishing step, the cameras judged
again between their neighbours, the undetermined ones dropped, then every camera judged. Policy
modules return verdicts (:mod:`stereoseed.sfm.hindsight`, :mod:`stereoseed.sfm.trust`); this
module applies them, through the model's own methods (:class:`~stereoseed.scene.reconstruction.Reconstruction`)."""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from stereoseed.config import Config
from stereoseed.scene.camera_life import Flag
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.correspondence import CorrespondenceSource, HarrisZncc
from stereoseed.sfm.hindsight import contradicted_by_neighbours, register_again
from stereoseed.sfm.loop_closure import judge_loop
from stereoseed.sfm.strategy import mode_of
from stereoseed.sfm.trust import Verdicts, contradicted_cameras, judge

__all__ = ["finish", "judge_cameras"]

log = logging.getLogger(__name__)


def finish(recon: Reconstruction, cfg: Config = Config(), source: CorrespondenceSource | None = None) -> dict[str, Any]:
    """After the last insertion: the mode's finishing step (accurate: loop closure, a final
    global BA, the no-zoom hold; paper: a global BA only with ``ba="final"``); a camera that its
    neighbours place clearly better elsewhere registered again there
    (:func:`stereoseed.sfm.hindsight.register_again`); the cameras left undetermined dropped;
    then each camera judged (:func:`judge_cameras`), and the loop with the cameras' uncertainty
    (:func:`stereoseed.sfm.loop_closure.judge_loop`). Returns the JSON-able report."""
    t = time.perf_counter()
    cfg = cfg.resolve()
    out = mode_of(cfg, recon).finish(recon, cfg, source or HarrisZncc(cfg))
    between: dict[int, Flag] | None = {}  # the neighbours' verdicts on the model as it is; None: not known
    if cfg.trust.judge_between_neighbours:
        found = register_again(recon, cfg, doubted=set(contradicted_cameras(recon, cfg)))
        between = None if found.registered_again else found.contradicted
        if found.registered_again:
            out["registered_again"] = {recon.views[v].name: what for v, what in found.registered_again.items()}
            out["registered_again_ba"] = found.ba
    dropped = _drop_undetermined_views(recon, cfg)
    if dropped:
        out["dropped"] = dropped
        between = None if cfg.trust.judge_between_neighbours else {}  # the model moved
    if between is None:  # the model moved since the neighbours judged it
        between = contradicted_by_neighbours(recon, cfg, doubted=set(contradicted_cameras(recon, cfg)))
    out["trust"] = _applied(recon, judge(recon, cfg, between), cfg)
    if isinstance(out.get("loop_closure"), dict):  # judged once every camera has its uncertainty
        judge_loop(recon, cfg, out["loop_closure"])
    out["seconds"] = time.perf_counter() - t
    return out


def judge_cameras(recon: Reconstruction, cfg: Config) -> dict[str, Any]:
    """Judge every registered camera of ``recon`` as the run's end does (:func:`stereoseed.sfm.trust.judge`,
    the neighbours' verdicts included with ``TrustConfig.judge_between_neighbours``) and apply the
    verdicts (:func:`_applied`); returns the report."""
    cfg = cfg.resolve()
    between = {}
    if cfg.trust.judge_between_neighbours:
        between = contradicted_by_neighbours(recon, cfg, doubted=set(contradicted_cameras(recon, cfg)))
    return _applied(recon, judge(recon, cfg, between), cfg)


def _applied(recon: Reconstruction, verdicts: Verdicts, cfg: Config) -> dict[str, Any]:
    """Each registered view judged (:meth:`Reconstruction.judge`) and given its uncertainty;
    without ``TrustConfig.keep_flagged``, the flagged views' observations removed (and the points
    left with fewer than two). Returns the JSON-able report: {image name: {"reliable",
    "flag_reason", "uncertainty"}} under "cameras", and {name: reason} under "flagged"."""
    cameras, flagged = {}, {}
    for v in recon.registered_views:
        view = recon.views[v]
        view.uncertainty = u = verdicts.uncertainties.get(v)
        recon.judge(v, verdicts.flags[v])
        cameras[view.name] = {"reliable": view.reliable, "flag_reason": view.flag_reason,
                              "uncertainty": None if u is None else u.summary()}
        if view.flag is not None:
            flagged[view.name] = view.flag_reason
            log.warning("%s: flagged, %s", view.name, view.flag_reason)
    if flagged and not cfg.trust.keep_flagged:
        out = np.isin(recon.obs_view, [v for v in recon.registered_views if not recon.views[v].reliable])
        recon.remove_observations(out)
        recon.remove_lonely_points()
    return {"cameras": cameras, "flagged": flagged}


def _drop_undetermined_views(recon: Reconstruction, cfg: Config) -> dict[str, str]:
    """Drop the moving camera's views left with fewer observations than a resection needs
    (``ResectionConfig.min_inliers``): outlier removal can strip a weakly placed view (the motion
    prior's camera from a dozen points) until nothing determines its camera, and a global BA then
    moves it anywhere (a dino view 0.4 m off went to 2.2 m on 9 observations). Returns
    {name: reason} of the views dropped."""
    dropped = {}
    counts = np.bincount(recon.obs_view, minlength=len(recon.views))
    for k in recon.registered_views:
        if k >= 2 and counts[k] < cfg.resection.min_inliers:
            reason = (f"{recon.views[k].name}: dropped at the end, only {counts[k]} observations left after outlier "
                      f"removal (a camera needs {cfg.resection.min_inliers}); its camera is not determined")
            recon.drop(k, reason)
            dropped[recon.views[k].name] = reason
            log.info("%s", reason)
    return dropped
