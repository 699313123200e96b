"""What the mapper's components are given: each its own configuration sections.

:class:`MapperOptions` gathers the sections the mapper (:mod:`stereoseed.sfm.mapper`) and its
strategies need, resolved (the mode's defaults filled in); it is built once at the top, from the
run's configuration (:meth:`stereoseed.config.Config.mapper_options`), as COLMAP's
``IncrementalMapper::Options`` gathers its components' options. The mapper hands each component
its own sections (``tracks.retriangulate(..., triangulation)``, ``refinement.drop_outliers(...,
outliers)``); the registrars get :class:`~stereoseed.sfm.registration.settings.RegistrationSettings`.
No module of ``sfm/`` reads the whole configuration or resolves it.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Protocol

from stereoseed.estimators.config import BundleConfig, ResectionConfig, TriangulationConfig
from stereoseed.features.config import FeatureConfig
from stereoseed.geometry.camera_model import CameraModel
from stereoseed.matching.config import MatchingConfig, PropagationConfig
from stereoseed.sfm.config import (LoopClosureConfig, MotionPriorConfig, OutlierConfig, PairCheckConfig, PipelineConfig,
                                   QuasiDenseConfig, RegistrationConfig, TrackingConfig, TrustConfig)
from stereoseed.sfm.registration.settings import RegistrationSettings

__all__ = ["MapperOptions", "Configuration", "options_of"]


@dataclass(frozen=True)
class MapperOptions:
    """The sections of a resolved configuration the mapper hands its components (each section
    as :class:`stereoseed.config.Config` holds it)."""

    features: FeatureConfig
    matching: MatchingConfig
    triangulation: TriangulationConfig
    resection: ResectionConfig
    bundle: BundleConfig
    propagation: PropagationConfig
    pipeline: PipelineConfig
    registration: RegistrationConfig
    outliers: OutlierConfig
    pair_check: PairCheckConfig
    trust: TrustConfig
    motion_prior: MotionPriorConfig
    tracking: TrackingConfig
    loop_closure: LoopClosureConfig
    quasi_dense: QuasiDenseConfig

    def __post_init__(self) -> None:
        pc = self.pipeline
        if (not isinstance(pc.camera_model, CameraModel) or pc.window is None or pc.ba is None
                or self.outliers.factor is None or self.motion_prior.explain_px is None):
            raise ValueError("MapperOptions takes a resolved configuration's sections (the mode's defaults filled "
                             "in): build it with stereoseed.config.Config.mapper_options()")

    def held(self) -> "MapperOptions":
        """The same options with the "fixed" camera model: the calibrated intrinsics, pose only
        (the accurate mode's no-zoom hold, a rig's cameras)."""
        return dataclasses.replace(self, pipeline=dataclasses.replace(self.pipeline, camera_model=CameraModel.FIXED))

    @functools.cached_property  # asked for at every insertion; the options never change
    def registering(self) -> RegistrationSettings:
        """The sections a registrar reads (:mod:`stereoseed.sfm.registration`)."""
        return RegistrationSettings(camera_model=self.pipeline.camera_model, resection=self.resection,
                                    registration=self.registration, motion_prior=self.motion_prior, trust=self.trust,
                                    quasi_dense=self.quasi_dense, propagation=self.propagation,
                                    triangulation=self.triangulation, matching=self.matching)


class Configuration(Protocol):
    """A configuration that gives its mapper options (:class:`stereoseed.config.Config`)."""

    def mapper_options(self) -> MapperOptions: ...


def options_of(given: MapperOptions | Configuration) -> MapperOptions:
    """``given`` itself, or a configuration's options (it resolves itself): the mapper's public
    steps take a plain :class:`~stereoseed.config.Config` too, as a notebook has one."""
    return given if isinstance(given, MapperOptions) else given.mapper_options()
