"""The sections a registrar reads (:mod:`stereoseed.sfm.registration`, :class:`stereoseed.sfm.rig.RigRegistrar`,
the hindsight's rivals): built by the mapper's options (:attr:`stereoseed.sfm.options.MapperOptions.registering`)."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.estimators.config import ResectionConfig, TriangulationConfig
from stereoseed.geometry.camera_model import CameraModel
from stereoseed.matching.config import MatchingConfig, PropagationConfig
from stereoseed.sfm.config import MotionPriorConfig, QuasiDenseConfig, RegistrationConfig, TrustConfig

__all__ = ["RegistrationSettings"]


@dataclass(frozen=True)
class RegistrationSettings:
    camera_model: CameraModel  # the run's moving camera (PipelineConfig.camera_model, resolved)
    resection: ResectionConfig
    registration: RegistrationConfig
    motion_prior: MotionPriorConfig  # resolved (its explain_px the mode's where left at None)
    trust: TrustConfig  # the ambiguity margins a registrar judges a choice by
    quasi_dense: QuasiDenseConfig
    propagation: PropagationConfig
    triangulation: TriangulationConfig
    matching: MatchingConfig
