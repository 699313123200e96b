"""A weak sparse outcome reconsidered (the registrar after the ambiguity judge): where the sparse
chain is weak, or failed, or the motion prior predicted the camera across views the walk could
not place, the quasi-dense registration (:mod:`stereoseed.sfm.registration.quasi_dense`) is
tried; the camera resting on more inliers is kept, and a weak sparse camera kept so must agree
with the propagated matches' epipolar geometry. Changes nothing in the model."""
from __future__ import annotations

import dataclasses
import logging

import numpy as np

from stereoseed.sfm.correspondence import CorrespondenceSource
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.config import QuasiDenseConfig
from stereoseed.sfm.registration.base import FailureKind, FoundBy, Registration, RegistrationFailure
from stereoseed.sfm.registration.settings import RegistrationSettings
from stereoseed.sfm.registration.quasi_dense import (QuasiDenseMatches, camera_epipolar_limit, epipolar_agreement,
                                                     register_quasi_dense, robust_f_agreement, weak_chain_limit)

__all__ = ["QuasiDenseRegistrar", "reconsider"]

log = logging.getLogger(__name__)


class QuasiDenseRegistrar:
    """Matches propagated from seeds between the last registered view and this one, tried when the
    sparse outcome is weak or failed (:func:`reconsider`)."""

    def register(self, recon: Reconstruction, source: CorrespondenceSource, k: int,
                 found: Registration | RegistrationFailure | None,
                 settings: RegistrationSettings) -> Registration | RegistrationFailure:
        if found is None:
            raise ValueError("the quasi-dense registrar reconsiders a sparse attempt; it cannot come first")
        return reconsider(recon, k, found, settings, source)


def reconsider(recon: Reconstruction, k: int, found: Registration | RegistrationFailure,
               settings: RegistrationSettings, source: CorrespondenceSource | None = None
               ) -> Registration | RegistrationFailure:
    """The sparse attempt ``found`` for view k, or the quasi-dense one when the sparse chain is
    weak (fewer resection inliers than :func:`weak_chain_limit`, or none, or the motion prior's
    camera predicted across views not placed) and the quasi-dense camera rests on more inliers.
    A camera placed across views not placed from a view flagged at its registration is refused
    (:func:`_unconfirmed`): the matches with that view only say how the two stand.
    Changes nothing in ``recon``; the choice is in ``notes``. With the quasi-dense registration
    off (``QuasiDenseConfig.enabled``) nothing is reconsidered, across a gap neither."""
    if not settings.quasi_dense.enabled or found.candidate is None:
        return found
    sparse_inliers = int(found.resection.inliers.sum()) if isinstance(found, Registration) else 0
    limit = weak_chain_limit(settings.quasi_dense, settings.motion_prior, settings.resection)
    prev = recon.registered_before(k, 1)[0]
    vp = recon.views[prev]
    if isinstance(found, Registration) and k - prev > 1 and vp.placement_flag:
        # placed across views not placed from a doubtful camera: any camera found here (this one,
        # the quasi-dense one) only says how it stands to that one
        return _unconfirmed(found, k, prev, f"from {vp.name}, flagged itself ({vp.placement_flag.kind.value})")
    if sparse_inliers >= limit and not _predicted_across_a_gap(found, k, prev):
        return found
    cand = found.candidate
    if sparse_inliers >= limit:
        why_weak = f"the motion prior's camera, predicted across {_views(k - prev - 1)}"
    elif isinstance(found, Registration):
        why_weak = f"{sparse_inliers} sparse resection inliers < {limit}"
    else:
        why_weak = found.reason
    try:
        attempt, qd = register_quasi_dense(recon, prev, cand, settings, source)
    except np.linalg.LinAlgError as e:  # a degenerate configuration the checks did not foresee
        attempt, qd = f"{cand.name}: numerical failure of the quasi-dense registration ({e})", None
    notes = {"sparse_weak": why_weak}

    def sparse_kept(seconds: dict[str, float]) -> Registration | RegistrationFailure:
        """The sparse outcome, with the attempt's notes: a camera checked, a failure extended."""
        if isinstance(found, Registration):
            return _weak_sparse_checked(recon, prev, dataclasses.replace(found, notes={**found.notes, **notes},
                                                                         seconds=seconds), qd,
                                        settings.quasi_dense)
        return dataclasses.replace(found, reason=f"{found.reason}; quasi-dense: {notes['quasi_dense_failed']}",
                                   notes=notes, seconds=seconds)

    if isinstance(attempt, str):
        log.info("quasi-dense registration of %s failed: %s", cand.name, attempt)
        notes["quasi_dense_failed"] = attempt
        return sparse_kept(found.seconds)
    seconds = {**found.seconds, **{f"quasi_dense_{s}": v for s, v in attempt.seconds.items()}}
    if attempt.resection.inliers.sum() < limit:  # no better founded than the weak chain it replaces
        notes["quasi_dense_failed"] = (f"{cand.name}: only {int(attempt.resection.inliers.sum())} quasi-dense "
                                       f"resection inliers (need {limit})")
        return sparse_kept(seconds)
    if sparse_inliers >= attempt.resection.inliers.sum():  # found is a Registration here
        notes["quasi_dense_inliers"] = int(attempt.resection.inliers.sum())
        return sparse_kept(seconds)
    log.info("%s registered by quasi-dense matches (%s)", cand.name, why_weak)
    return dataclasses.replace(attempt, seconds=seconds, notes=notes)


def _predicted_across_a_gap(found: Registration | RegistrationFailure, k: int, prev: int) -> bool:
    """Whether ``found`` is the motion prior's camera predicted over views the walk could not
    place (k more than one step after prev): the previous motion extrapolated that far proves
    little, whatever the inliers (a plain box's squares matched one face over, 1.8 m off)."""
    return isinstance(found, Registration) and found.found_by == FoundBy.MOTION_PRIOR and k - prev > 1


def _views(n: int) -> str:
    return f"{n} view{'' if n == 1 else 's'} not placed"


def _unconfirmed(found: Registration, k: int, prev: int, why: str) -> RegistrationFailure:
    """The refusal of ``found``, placed across views not placed since ``prev``, that nothing
    confirms (``why``): ``FailureKind.UNCONFIRMED``, no evidence against the previous view (the
    mapper withdraws none for it)."""
    return _refused(found, f"{found.candidate.name}: the {found.found_by} camera, placed across "
                           f"{_views(k - prev - 1)}, {why}", FailureKind.UNCONFIRMED)


def _refused(found: Registration, reason: str, kind: FailureKind) -> RegistrationFailure:
    """The sparse camera ``found`` refused for ``reason`` (also its notes' "sparse_refused")."""
    log.info("%s", reason)
    return RegistrationFailure(reason, found.matches, found.chained_points, found.seconds, found.candidate,
                               notes={**found.notes, "sparse_refused": reason}, kind=kind, flag=found.flag)


def _weak_sparse_checked(recon: Reconstruction, prev: int, found: Registration, qd: QuasiDenseMatches | None,
                         quasi_dense: QuasiDenseConfig) -> Registration | RegistrationFailure:
    """The weak sparse camera ``found`` kept after the quasi-dense attempt, refused when it
    disagrees with the propagated matches' epipolar geometry as a quasi-dense camera would be
    (``QuasiDenseConfig.camera_epipolar_factor``); unchanged when there is no robust F. The
    motion prior's camera across a gap (:func:`_predicted_across_a_gap`) is refused without a
    robust F (:func:`_unconfirmed`)."""
    k = found.candidate.index
    if qd is None or qd.F is None:
        if _predicted_across_a_gap(found, k, prev):
            return _unconfirmed(found, k, prev, f"without propagated matches with {recon.views[prev].name} to confirm it")
        return found
    floor = robust_f_agreement(qd)
    agrees = epipolar_agreement(recon.views[prev].P, found.P, qd)
    if agrees <= camera_epipolar_limit(floor, quasi_dense):
        return found
    return _refused(found, f"{found.candidate.name}: the weak {found.found_by} camera "
                           f"({int(found.resection.inliers.sum())} inliers) disagrees with the propagated matches "
                           f"(their median distance to its epipolar lines {agrees:.2f} px, to the robust F's "
                           f"{floor:.2f} px)", FailureKind.DISAGREES)
