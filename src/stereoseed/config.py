"""All tunable parameters, gathered in :class:`Config`: one frozen dataclass per stage, each
defined beside the package it tunes (``features/config.py``, ``sfm/config.py``, ...) and
validated when it is built; :meth:`Config.resolve` fills the mode's defaults in, once.

Every default states its source. "paper" is "Incremental Multi-view 3D Reconstruction Starting
from Two Images Taken by a Stereo Pair of Cameras" (see ../shared/paper.md); "LQ02" is
Lhuillier & Quan, "Match propagation for image-based modeling and rendering", PAMI 2002;
"HZ" is Hartley & Zisserman, Multiple View Geometry, 2nd ed.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from stereoseed.features.config import FeatureConfig
from stereoseed.matching.config import MatchingConfig, PropagationConfig
from stereoseed.estimators.config import TriangulationConfig, ResectionConfig, BundleConfig
from stereoseed.dense.config import DenseConfig
from stereoseed.io.config import VideoConfig
from stereoseed.output.config import ExportConfig
from stereoseed.sfm.config import (LoopClosureConfig, MotionPriorConfig, OutlierConfig, PairCheckConfig, PipelineConfig,
                                  QuasiDenseConfig, RegistrationConfig, TrackingConfig, TrustConfig)

__all__ = ["Config", "ResolvedConfig", "FeatureConfig", "MatchingConfig", "PropagationConfig", "TriangulationConfig",
           "ResectionConfig", "BundleConfig", "DenseConfig", "VideoConfig", "QuasiDenseConfig", "MotionPriorConfig",
           "TrackingConfig", "LoopClosureConfig", "PipelineConfig", "RegistrationConfig", "OutlierConfig",
           "PairCheckConfig", "ExportConfig", "TrustConfig"]


@dataclass(frozen=True)
class Config:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    resection: ResectionConfig = field(default_factory=ResectionConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    propagation: PropagationConfig = field(default_factory=PropagationConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    outliers: OutlierConfig = field(default_factory=OutlierConfig)
    pair_check: PairCheckConfig = field(default_factory=PairCheckConfig)
    trust: TrustConfig = field(default_factory=TrustConfig)
    motion_prior: MotionPriorConfig = field(default_factory=MotionPriorConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    quasi_dense: QuasiDenseConfig = field(default_factory=QuasiDenseConfig)
    video: VideoConfig = field(default_factory=VideoConfig)
    export: ExportConfig = field(default_factory=ExportConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if not isinstance(getattr(self, f.name), f.default_factory):
                raise ValueError(f"Config.{f.name} must be a {f.default_factory.__name__}, "
                                 f"got {type(getattr(self, f.name)).__name__}")

    def resolve(self) -> "ResolvedConfig":
        """The configuration a run uses: the mode-dependent defaults (None) filled in, once (a
        :class:`ResolvedConfig` resolves to itself)."""
        pipeline = self.pipeline.resolved()
        defaults = pipeline.defaults
        prior, outliers = self.motion_prior, self.outliers
        if prior.explain_px is None:
            prior = dataclasses.replace(prior, explain_px=defaults.explain_px)
        if outliers.factor is None:
            outliers = dataclasses.replace(outliers, factor=defaults.outlier_factor)
        sections = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return ResolvedConfig(**{**sections, "pipeline": pipeline, "motion_prior": prior, "outliers": outliers})

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration as a JSON-able dict (what report.json records)."""
        return dataclasses.asdict(self.resolve())

    def replace(self, **sections: Any) -> "Config":
        """Copy with some stages' fields replaced: ``cfg.replace(matching={"min_zncc": 0.7})``."""
        updates = {}
        for name, values in sections.items():
            current = getattr(self, name)
            updates[name] = dataclasses.replace(current, **values) if isinstance(values, dict) else values
        return dataclasses.replace(self, **updates)


@dataclass(frozen=True)
class ResolvedConfig(Config):
    """A :class:`Config` with every mode-dependent default filled in: what a run's steps read.
    The public entry points resolve the configuration they are given once; the steps below them
    take this type and do not resolve again."""

    def resolve(self) -> "ResolvedConfig":
        return self

    def replace(self, **sections: Any) -> "ResolvedConfig":
        """Copy with some stages' fields replaced, still resolved (a field set to None takes its
        mode's default again)."""
        plain = Config(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        return plain.replace(**sections).resolve()
