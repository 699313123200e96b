"""Configurations validate when built and report.json records the resolved one."""
import json

import pytest

from stereoseed.config import (BundleConfig, Config, LoopClosureConfig, MotionPriorConfig, PipelineConfig,
                               PropagationConfig, ResectionConfig, TriangulationConfig)


@pytest.mark.parametrize("make, field", [
    (lambda: PipelineConfig(mode="acurate"), "mode"),
    (lambda: PipelineConfig(ba="globl"), "ba"),
    (lambda: PipelineConfig(window=0), "window"),
    (lambda: PipelineConfig(window=-1), "window"),
    (lambda: PipelineConfig(camera_model="pinhole"), "camera_model"),
    (lambda: PipelineConfig(min_chained_points=4), "min_chained_points"),
    (lambda: PipelineConfig(outlier_factor=-1.0), "outlier_factor"),
    (lambda: ResectionConfig(min_inliers=3), "min_inliers"),
    (lambda: ResectionConfig(ransac_threshold_px=0.0), "ransac_threshold_px"),
    (lambda: TriangulationConfig(min_angle_deg=-1.0), "min_angle_deg"),
    (lambda: BundleConfig(global_rounds=0), "global_rounds"),
    (lambda: PropagationConfig(window=4), "window"),
    (lambda: MotionPriorConfig(radius_fractions=()), "radius_fractions"),
    (lambda: LoopClosureConfig(span=0), "span"),
    (lambda: Config(pipeline={"mode": "paper"}), "pipeline"),
])
def test_invalid_configs_are_refused_with_the_field_named(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_the_resolved_config_fills_in_the_mode_defaults():
    paper = Config(pipeline=PipelineConfig(mode="paper")).resolved()
    assert (paper.pipeline.camera_model, paper.pipeline.window, paper.pipeline.ba) == ("free", 1, "local")
    assert paper.pipeline.resolved_outlier_factor() is None and paper.motion_prior.explain_px == 3.0
    accurate = Config().resolved()
    assert (accurate.pipeline.camera_model, accurate.pipeline.window, accurate.pipeline.ba) == ("focal", 3, "final")
    assert accurate.pipeline.resolved_outlier_factor() == 4.0 and accurate.motion_prior.explain_px == 1.5
    assert accurate.resolved() == accurate
    # what the user set stays
    mine = Config(pipeline=PipelineConfig(mode="paper", window=2, ba="final")).resolved().pipeline
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
