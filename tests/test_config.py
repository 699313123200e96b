"""Configurations validate when built and report.json records the resolved one."""
import json

import pytest

from stereoseed.config import (BundleConfig, Config, ExportConfig, OutlierConfig, PairCheckConfig, RegistrationConfig,
                               ResolvedConfig, LoopClosureConfig, MotionPriorConfig, PipelineConfig,
                               PropagationConfig, ResectionConfig, TriangulationConfig)


@pytest.mark.parametrize("make, field", [
    (lambda: PipelineConfig(mode="acurate"), "mode"),
    (lambda: PipelineConfig(ba="globl"), "ba"),
    (lambda: PipelineConfig(window=0), "window"),
    (lambda: PipelineConfig(window=-1), "window"),
    (lambda: PipelineConfig(camera_model="pinhole"), "camera_model"),
    (lambda: RegistrationConfig(min_chained_points=4), "min_chained_points"),
    (lambda: OutlierConfig(factor=-1.0), "factor"),
    (lambda: OutlierConfig(max_px=0.0), "max_px"),
    (lambda: PairCheckConfig(min_consistent=1.5), "min_consistent"),
    (lambda: ExportConfig(far_point_factor=0.0), "far_point_factor"),
    (lambda: ResectionConfig(min_inliers=3), "min_inliers"),
    (lambda: ResectionConfig(ransac_threshold_px=0.0), "ransac_threshold_px"),
    (lambda: TriangulationConfig(min_angle_deg=-1.0), "min_angle_deg"),
    (lambda: BundleConfig(global_rounds=0), "global_rounds"),
    (lambda: PropagationConfig(window=4), "window"),
    (lambda: MotionPriorConfig(radius_fractions=()), "radius_fractions"),
    (lambda: LoopClosureConfig(span=0), "span"),
    (lambda: Config(pipeline={"mode": "paper"}), "pipeline"),
    (lambda: RegistrationConfig(max_zoom_step=1.0), "max_zoom_step"),
    (lambda: PipelineConfig(window=True), "window"),
    (lambda: PipelineConfig(window=2.5), "window"),
    (lambda: MotionPriorConfig(wider_search_margin=0.9), "wider_search_margin"),
    (lambda: MotionPriorConfig(pairings_per_point=(3, 4.5)), "pairings_per_point"),
    (lambda: LoopClosureConfig(span=2.5), "span"),
    (lambda: ResectionConfig(ransac_confidence=0.0), "ransac_confidence"),
])
def test_invalid_configs_are_refused_with_the_field_named(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_the_resolved_config_fills_in_the_mode_defaults():
    paper = Config(pipeline=PipelineConfig(mode="paper")).resolve()
    assert (paper.pipeline.camera_model, paper.pipeline.window, paper.pipeline.ba) == ("free", 1, "local")
    assert paper.outliers.active_factor() is None and paper.motion_prior.explain_px == 3.0
    accurate = Config().resolve()
    assert (accurate.pipeline.camera_model, accurate.pipeline.window, accurate.pipeline.ba) == ("focal", 3, "final")
    assert accurate.outliers.active_factor() == 4.0 and accurate.motion_prior.explain_px == 1.5
    assert isinstance(accurate, ResolvedConfig) and accurate.resolve() is accurate  # resolved once
    # a copy with a field changed stays resolved; a field set back to None takes its mode's default again
    fixed = accurate.replace(pipeline={"camera_model": "fixed"})
    assert isinstance(fixed, ResolvedConfig) and fixed.pipeline.camera_model == "fixed" and fixed.pipeline.window == 3
    assert fixed.replace(pipeline={"camera_model": None}).pipeline.camera_model == "focal"
    # what the user set stays
    mine = Config(pipeline=PipelineConfig(mode="paper", window=2, ba="final")).resolve().pipeline
    assert (mine.window, mine.ba) == (2, "final")


def test_the_config_dict_is_the_resolved_one_and_json_able():
    d = json.loads(json.dumps(Config(pipeline=PipelineConfig(mode="paper")).to_dict()))
    assert d["pipeline"]["camera_model"] == "free" and d["pipeline"]["window"] == 1
    assert d["motion_prior"]["explain_px"] == 3.0


def test_replace_validates_the_new_values():
    cfg = Config().replace(pipeline={"camera_model": "fixed"})
    assert cfg.pipeline.camera_model == "fixed"
    with pytest.raises(ValueError, match="window"):
        Config().replace(pipeline={"window": 0})


def test_whole_numbers_and_sequences_are_normalised():
    import numpy as np

    assert PipelineConfig(window=np.int64(2)).window == 2
    prior = MotionPriorConfig(radius_fractions=[0.1, 0.2], pairings_per_point=[2])
    assert prior.radius_fractions == (0.1, 0.2) and prior.pairings_per_point == (2,)
    hash(Config(motion_prior=prior))  # frozen and hashable: usable as a cache key


def test_dense_workers_default_to_the_cores():
    from stereoseed.config import DenseConfig
    from stereoseed.threads import CORES

    assert DenseConfig().pool_size() == CORES and DenseConfig(workers=3).pool_size() == 3
    with pytest.raises(ValueError, match="workers"):
        DenseConfig(workers=-1)
