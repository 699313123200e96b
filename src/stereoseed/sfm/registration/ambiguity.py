"""An ambiguous registration (a repeated pattern: a rival camera a period away explains nearly as
much, :func:`stereoseed.sfm.registration.base.ambiguous_rivals`) judged by more evidence than the points
that chose it: the matches propagated between the previous view and this one, which cover the
whole overlap, the pattern's ends and everything around it included (Lhuillier & Quan's
propagation, as the quasi-dense registration runs it). Only the flag is judged, never the
choice: choosing by these matches changed later insertions (docs/mapper.md, "Trust")."""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from stereoseed.sfm.correspondence import CorrespondenceSource
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.registration.base import Registration, RegistrationFailure
from stereoseed.sfm.registration.settings import RegistrationSettings
from stereoseed.sfm.registration.quasi_dense import (propagated_to_candidate, camera_epipolar_limit,
                                                     epipolar_agreement, robust_f_agreement)

__all__ = ["AmbiguityJudge", "judge_ambiguity"]

log = logging.getLogger(__name__)


class AmbiguityJudge:
    """The sparse registrar's ambiguous choice judged (:func:`judge_ambiguity`); any other
    outcome passed on as it is."""

    def register(self, recon: Reconstruction, source: CorrespondenceSource, k: int,
                 found: Registration | RegistrationFailure | None,
                 settings: RegistrationSettings) -> Registration | RegistrationFailure:
        if found is None:
            raise ValueError("the ambiguity judge judges a sparse attempt; it cannot come first")
        if not (isinstance(found, Registration) and found.rivals):  # rivals: the choice is flagged
            return found
        return judge_ambiguity(recon, recon.registered_before(k, 1)[0], found, settings, source)


def judge_ambiguity(recon: Reconstruction, prev: int, found: Registration, settings: RegistrationSettings,
                    source: CorrespondenceSource | None = None) -> Registration:
    """The ambiguous choice ``found`` (its ``flag`` and ``rivals``) judged by more evidence:
    the matches propagated between the previous view and this one, which cover the whole
    overlap, the pattern's ends and everything around it included. The flag is lifted when the
    winner agrees with their epipolar geometry (:func:`camera_epipolar_limit`) and every rival
    lies at least ``rival_epipolar_factor`` times farther from them than the winner; otherwise
    it stays, with the evidence in the notes. The choice itself never changes here. The matches
    only say how the two cameras stand to each other: a previous view that is flagged itself (a
    walk that carries an offset keeps it between consecutive views; on a rig, either image of
    its station) cannot lift a flag. Without rivals, or with the propagation off
    (``QuasiDenseConfig.enabled``), ``found`` is returned as it is."""
    qc = settings.quasi_dense
    if not found.rivals or not qc.enabled:
        return found
    # a rig's station is one body: its flag sits on the image it was resected from (views 2s, 2s+1)
    station = (prev, prev ^ 1) if recon.rig is not None and (prev ^ 1) < len(recon.views) else (prev,)
    flagged = next((recon.views[v].name for v in station if recon.views[v].placement_flag), None)
    if flagged is not None:
        return dataclasses.replace(found, notes={**found.notes, "ambiguity": f"unresolved: the previous view, "
                                                 f"{flagged}, is flagged itself"})
    try:
        # only the grid's matches are read (the robust F and the agreement): only they are refined
        qd = propagated_to_candidate(recon, source, prev, found.candidate, qc, settings.propagation,
                                     settings.matching, lambda: np.zeros((0, 2)))
    except np.linalg.LinAlgError as e:  # a degenerate configuration: no evidence, the flag stays
        return dataclasses.replace(found, notes={**found.notes, "ambiguity": f"unresolved: numerical failure ({e})"})
    if qd.F is None:
        return dataclasses.replace(found, notes={**found.notes, "ambiguity": "no robust F on the propagated matches"})
    floor = robust_f_agreement(qd)
    P_prev = recon.views[prev].P
    winner = epipolar_agreement(P_prev, found.P, qd)
    rival = min(epipolar_agreement(P_prev, P, qd) for P in found.rivals)
    evidence = (f"the propagated matches lie {winner:.2f} px from its epipolar lines, {rival:.2f} px from the "
                f"nearest rival's (the robust F's own {floor:.2f} px)")
    if winner <= camera_epipolar_limit(floor, qc) and rival >= qc.rival_epipolar_factor * winner:
        log.info("%s: the repeated structure's ambiguity is resolved: %s", found.candidate.name, evidence)
        return dataclasses.replace(found, flag=None, notes={**found.notes, "ambiguity_resolved": evidence})
    return dataclasses.replace(found, notes={**found.notes, "ambiguity": f"unresolved: {evidence}"})
