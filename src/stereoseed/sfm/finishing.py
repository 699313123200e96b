"""The end of the run (after the last insertion): the mode's finishing step, the cameras judged
again between their neighbours, the undetermined ones dropped, then every camera judged. Policy
modules return verdicts (:mod:`stereoseed.sfm.hindsight`, :mod:`stereoseed.sfm.trust`); this
module applies them, through the model's own methods (:class:`~stereoseed.scene.reconstruction.Reconstruction`)."""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import numpy as np

from stereoseed.estimators.config import ResectionConfig
from stereoseed.sfm.config import TrustConfig
from stereoseed.scene.camera_life import Flag
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.correspondence import CorrespondenceSource, HarrisZncc
from stereoseed.sfm.hindsight import contradicted_by_neighbours, register_again
from stereoseed.sfm.loop_closure import judge_loop
from stereoseed.sfm.pair_consistency import pair_consistency
from stereoseed.sfm.refinement import CALIBRATED
from stereoseed.sfm.options import Configuration, MapperOptions, options_of
from stereoseed.sfm.strategy import mode_of
from stereoseed.sfm.trust import Verdicts, contradicted_cameras, judge

__all__ = ["finish", "judge_cameras"]

log = logging.getLogger(__name__)


def finish(recon: Reconstruction, options: MapperOptions | Configuration,
           source: CorrespondenceSource | None = None) -> dict[str, Any]:
    """After the last insertion: the mode's finishing step (accurate: loop closure, a final
    global BA, the no-zoom hold; paper: a global BA only with ``ba="final"``); a camera that its
    neighbours place clearly better elsewhere registered again there
    (:func:`stereoseed.sfm.hindsight.register_again`); the cameras left undetermined dropped;
    then each camera judged (:func:`judge_cameras`), and the loop with the cameras' uncertainty
    (:func:`stereoseed.sfm.loop_closure.judge_loop`); how well the calibrated pair agrees with
    the walk placed from it (:func:`stereoseed.sfm.pair_consistency.pair_consistency`, not a
    rig walk's). ``options``: the mapper's (a plain
    :class:`~stereoseed.config.Config` gives its own). Returns the JSON-able report."""
    t = time.perf_counter()
    options = options_of(options)
    out = mode_of(options.pipeline, recon).finish(recon, options, source or HarrisZncc.of(options))
    tc = options.trust
    between: dict[int, Flag] | None = {}  # the neighbours' verdicts on the model as it is; None: not known
    if tc.judge_between_neighbours:
        found = register_again(recon, options, doubted=set(contradicted_cameras(recon, tc)))
        between = None if found.registered_again else found.contradicted
        if found.registered_again:
            out["registered_again"] = {recon.views[v].name: what for v, what in found.registered_again.items()}
            out["registered_again_ba"] = found.ba
    dropped = _drop_undetermined_views(recon, options.resection)
    if dropped:
        out["dropped"] = dropped
        between = None if tc.judge_between_neighbours else {}  # the model moved
    if between is None:  # the model moved since the neighbours judged it
        between = contradicted_by_neighbours(recon, options.registering, doubted=set(contradicted_cameras(recon, tc)))
    out["trust"] = _applied(recon, _verdicts(recon, options, between), tc)
    if isinstance(out.get("loop_closure"), dict):  # judged once every camera has its uncertainty
        judge_loop(recon, options.loop_closure, out["loop_closure"])
    if recon.rig is None:  # a rig walk's pair is its first station, adjusted with the rig
        # the pairs the BA would keep (OutlierConfig.max_px), counted as its covariance counts them
        out["pair_consistency"] = pair_consistency(recon, CALIBRATED, tc.independent_cell_px,
                                                   options.outliers.max_px)
    out["seconds"] = time.perf_counter() - t
    return out


def judge_cameras(recon: Reconstruction, options: MapperOptions | Configuration) -> dict[str, Any]:
    """Judge every registered camera of ``recon`` as the run's end does (:func:`stereoseed.sfm.trust.judge`,
    the neighbours' verdicts included with ``TrustConfig.judge_between_neighbours``) and apply the
    verdicts (:func:`_applied`); returns the report."""
    options = options_of(options)
    tc = options.trust
    between = {}
    if tc.judge_between_neighbours:
        between = contradicted_by_neighbours(recon, options.registering, doubted=set(contradicted_cameras(recon, tc)))
    return _applied(recon, _verdicts(recon, options, between), tc)


def _verdicts(recon: Reconstruction, options: MapperOptions, between: dict[int, Flag]) -> Verdicts:
    """:func:`stereoseed.sfm.trust.judge` given its sections; the cameras' uncertainty under the
    camera model of the mode's BA (:meth:`~stereoseed.sfm.modes.Mode.adjustment_options`)."""
    model = mode_of(options.pipeline, recon).adjustment_options(recon, options).pipeline.camera_model
    trust = options.trust
    if options.pipeline.ba == "local":
        # the residuals' spread is measured about a least-squares solution, which a model of
        # local adjustments only is not (the paper's mode: its shared gradient would pass for
        # spread, and its experiments are reproduced as the paper ran them)
        trust = dataclasses.replace(trust, spread_cell_px=None)
    return judge(recon, between, trust=trust, resection=options.resection,
                 motion_prior=options.motion_prior, model=model)


def _applied(recon: Reconstruction, verdicts: Verdicts, trust: TrustConfig) -> dict[str, Any]:
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
    if flagged and not trust.keep_flagged:
        out = np.isin(recon.obs_view, [v for v in recon.registered_views if not recon.views[v].reliable])
        recon.remove_observations(out)
        recon.remove_lonely_points()
    return {"cameras": cameras, "flagged": flagged}


def _drop_undetermined_views(recon: Reconstruction, resection: ResectionConfig) -> dict[str, str]:
    """Drop the moving camera's views left with fewer observations than a resection needs
    (``ResectionConfig.min_inliers``): outlier removal can strip a weakly placed view (the motion
    prior's camera from a dozen points) until nothing determines its camera, and a global BA then
    moves it anywhere (a dino view 0.4 m off went to 2.2 m on 9 observations). Returns
    {name: reason} of the views dropped."""
    dropped = {}
    counts = np.bincount(recon.obs_view, minlength=len(recon.views))
    for k in recon.registered_views:
        if k >= 2 and counts[k] < resection.min_inliers:
            reason = (f"{recon.views[k].name}: dropped at the end, only {counts[k]} observations left after outlier "
                      f"removal (a camera needs {resection.min_inliers}); its camera is not determined")
            recon.drop(k, reason)
            dropped[recon.views[k].name] = reason
            log.info("%s", reason)
    return dropped
