"""Which strategy a run follows: the mode's (:mod:`stereoseed.sfm.modes`) or, on a stereo rig's
walk, the rig's (:mod:`stereoseed.sfm.rig`), and the registrars that place its views, in order.
Above both modules, so that neither imports the other."""
from __future__ import annotations

from stereoseed.sfm.config import PipelineConfig
from stereoseed.scene.reconstruction import Reconstruction
from stereoseed.sfm.modes import AccurateMode, Mode, PaperMode
from stereoseed.sfm.registration.ambiguity import AmbiguityJudge
from stereoseed.sfm.registration.base import Registrar, SparseRegistrar
from stereoseed.sfm.registration.reconsider import QuasiDenseRegistrar
from stereoseed.sfm.rig import RigMode, RigRegistrar

__all__ = ["mode_of", "registrars"]


def mode_of(pipeline: PipelineConfig, recon: Reconstruction | None = None) -> Mode:
    """The strategy of ``pipeline.mode``; a rig walk's (``recon.rig``) its own
    (:class:`stereoseed.sfm.rig.RigMode`)."""
    if recon is not None and recon.rig is not None:
        return RigMode()
    return PaperMode() if pipeline.mode == "paper" else AccurateMode()


def registrars(recon: Reconstruction | None = None) -> tuple[Registrar, ...]:
    """The registrars tried for each view, in order: the sparse matches (epipolar chain against the
    motion prior), the judge of an ambiguous choice, then the quasi-dense matches where the
    sparse outcome is weak (a registrar that does not apply returns the outcome it was given). A
    rig walk's (``recon.rig``): its stations' generalised resection
    (:class:`stereoseed.sfm.rig.RigRegistrar`)."""
    if recon is not None and recon.rig is not None:
        return (RigRegistrar(),)
    return (SparseRegistrar(), AmbiguityJudge(), QuasiDenseRegistrar())
