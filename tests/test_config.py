"""Configurations validate when built and report.json records the resolved one."""
import json
import tomllib

import pytest

from stereoseed.config import (BundleConfig, Config, ExportConfig, OutlierConfig, PairCheckConfig, RegistrationConfig,
                               ResolvedConfig, LoopClosureConfig, MotionPriorConfig, PipelineConfig,
                               PropagationConfig, QuasiDenseConfig, ResectionConfig, TriangulationConfig)


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
    (lambda: PairCheckConfig(min_known_ratio=1.5), "min_known_ratio"),
    (lambda: QuasiDenseConfig(rival_epipolar_factor=0.5), "rival_epipolar_factor"),
    (lambda: QuasiDenseConfig(camera_epipolar_factor=0.5), "camera_epipolar_factor"),
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


def test_the_mapper_options_are_the_resolved_sections_each_component_is_handed():
    import dataclasses

    from stereoseed.sfm.options import MapperOptions, options_of

    cfg = Config(pipeline=PipelineConfig(mode="paper"), outliers=OutlierConfig(max_px=3.0))
    options, resolved = cfg.mapper_options(), cfg.resolve()
    assert all(getattr(options, f.name) == getattr(resolved, f.name) for f in dataclasses.fields(MapperOptions))
    assert options.pipeline.camera_model == "free" and options.outliers.factor == 0.0  # the paper mode's
    # held(): what the BA holding the intrinsics ran on before (the resolved configuration's replace)
    held = resolved.replace(pipeline={"camera_model": "fixed"})
    assert options.held().pipeline == held.pipeline and options.held().bundle is options.bundle
    assert options.registering.camera_model == "free" and options.registering.trust is options.trust
    assert options_of(cfg) == options and options_of(options) is options  # a plain Config gives its own
    with pytest.raises(ValueError, match="resolved"):  # the mode's defaults left at None
        MapperOptions(**{f.name: getattr(Config(), f.name) for f in dataclasses.fields(MapperOptions)})


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


# --- configuration files (docs/config.md) -----------------------------------------------------
import dataclasses  # noqa: E402
import typing  # noqa: E402

from stereoseed.cli import main  # noqa: E402
from stereoseed.config import ConfigError  # noqa: E402

_WORDS = ("paper", "accurate", "free", "zero-skew", "focal", "fixed", "local", "global", "final", "affine", "quadratic",
          "auto", "images", "as-given")


def _candidates(hint, default):
    """Values other than ``default`` a field of type ``hint`` may take, most likely valid first."""
    if typing.get_origin(hint) in (typing.Union, type(int | None)):
        inner = [a for a in typing.get_args(hint) if a is not type(None)][0]
        if default is not None:
            return [None]
        return {int: [12, 2, 1], float: [0.5, 2.0, 0.05], str: list(_WORDS)}[inner]
    if typing.get_origin(hint) is tuple:
        return [default + default[-1:], tuple(2 * v for v in default)]
    if hint is bool:
        return [not default]
    if hint is int:
        return [default + 1, default + 2, default - 1]
    if hint is float:
        return [default * 1.1, default * 0.9, default + 0.5] if default else [0.5, 1.0]
    return [w for w in _WORDS if w != default]


def _toml(value):
    if value is None:
        return '"none"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return json.dumps(value)


def test_every_field_of_config_is_set_from_a_toml_file(tmp_path):
    """Each field of each section set to a value other than its default (the first its dataclass
    accepts), all in one file: each comes back as written."""
    chosen, lines = {}, []
    for section in dataclasses.fields(Config):
        default = section.default_factory()
        hints = typing.get_type_hints(type(default))
        lines.append(f"[{section.name}]")
        for f in dataclasses.fields(default):
            value = getattr(default, f.name)
            for candidate in _candidates(hints[f.name], value):
                try:
                    dataclasses.replace(default, **{f.name: candidate})
                except ValueError:
                    continue
                chosen[section.name, f.name] = candidate
                lines.append(f"{f.name} = {_toml(candidate)}")
                break
    path = tmp_path / "every.toml"
    path.write_text("\n".join(lines) + "\n")
    cfg = Config.from_toml(path)
    n_fields = sum(len(dataclasses.fields(s.default_factory)) for s in dataclasses.fields(Config))
    assert len(chosen) == n_fields > 120  # not one field without a value of its own
    for (section, name), value in chosen.items():
        got, default = getattr(getattr(cfg, section), name), getattr(getattr(Config(), section), name)
        assert got == value and type(got) is type(value) and got != default, (section, name, got, value)


@pytest.mark.parametrize("cfg", [Config(), Config(pipeline=PipelineConfig(mode="paper", window=2)),
                                 Config().replace(matching={"max_ratio": None, "scales": (0.9, 1.1)},
                                                  quasi_dense={"background_grey": None})])
def test_the_resolved_config_round_trips_through_toml_and_report_json(cfg, tmp_path):
    resolved = cfg.resolve()
    path = tmp_path / "cfg.toml"
    path.write_text(cfg.to_toml())
    assert Config.from_toml(path).resolve() == resolved
    as_json = json.loads(json.dumps(cfg.to_dict()))  # what report.json holds
    again = Config.from_dict(as_json)
    assert again.resolve() == resolved and hash(again.resolve()) == hash(resolved)
    assert again.to_dict() == cfg.to_dict() and again.to_toml() == cfg.to_toml()
    (tmp_path / "report.json").write_text(json.dumps({"images": 3, "config": as_json}))
    assert Config.from_file(tmp_path / "report.json").resolve() == resolved


@pytest.mark.parametrize("text, says", [
    ('[matching]\nmin_znc = 0.7\n', "[matching] unknown key 'min_znc' (did you mean min_zncc?)"),
    ('[matchng]\nmin_zncc = 0.7\n', "unknown section 'matchng' (did you mean matching?)"),
    ('mode = "paper"\n', "unknown section 'mode'; settings go in their section's table: [pipeline] mode"),
    ('[pipeline]\nwindow = 0\n', "[pipeline] window = 0: PipelineConfig.window must be a whole number >= 1"),
    ('[pipeline]\nmode = "fast"\n', "[pipeline] mode = \"fast\": PipelineConfig.mode must be one of paper, accurate"),
    ('[features]\nmax_corners = "many"\n', "[features] max_corners = \"many\": expected a whole number"),
    ('[features]\nharris_k = "none"\n', "[features] harris_k = \"none\": expected a number"),
    ('[motion_prior]\nradius_fractions = 0.1\n', "[motion_prior] radius_fractions = 0.1: expected an array of numbers"),
    ('[resection]\nmin_points = 9\nmin_inliers = 8\n', "[resection] min_points, min_inliers: ResectionConfig"),
    ('[pipeline\nmode = "paper"\n', "not valid TOML"),
    ("[pipeline]\nmode = " + "[" * 100000 + "]" * 100000 + "\n", "nested more than 64 levels deep"),  # RecursionError
    # issue 48 row 11: tracebacks deep in a run, or a cloud of 0 or 1 points
    ('[features]\nmax_corners = 3000000000\n', "max_corners = 3000000000: expected a whole number within +-2147483647"),
    ('[matching]\nseed = 9223372036854775807\n', "seed = 9223372036854775807: expected a whole number within"),
    ('[matching]\npatch_size = 100001\n', "patch_size = 100001: MatchingConfig: patch_size must be an odd positive "
                                           "integer up to 101"),
    ('[dense]\nfusion_voxel = nan\n', "fusion_voxel = NaN: expected a finite number"),
    ('[dense]\nfusion_voxel = inf\n', "fusion_voxel = Infinity: expected a finite number"),
])
def test_a_bad_config_file_is_one_line_naming_the_file_and_the_key(text, says, tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as refused:
        Config.from_toml(path)
    assert str(refused.value).startswith(f"{path}: ") and says in str(refused.value)
    out = tmp_path / "out"
    assert main(["reconstruct", str(tmp_path), "--calib", str(tmp_path / "c.json"), "--out", str(out),
                 "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"stereoseed: error: {refused.value}\n" and not out.exists()  # refused before any work


def test_command_line_options_override_the_file(tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text('[pipeline]\nmode = "paper"\nwindow = 2\n\n[matching]\nmin_zncc = 0.7\n')

    def shown(*options):
        assert main(["config", "--config", str(path), *options]) == 0
        return Config.from_dict(tomllib.loads(capsys.readouterr().out))

    plain = shown()
    assert (plain.pipeline.mode, plain.pipeline.window, plain.pipeline.camera_model) == ("paper", 2, "free")
    assert plain.matching.min_zncc == 0.7 and plain.trust.keep_flagged is False
    over = shown("--window", "4", "--camera-model", "fixed", "--keep-flagged")
    assert (over.pipeline.mode, over.pipeline.window, over.pipeline.camera_model) == ("paper", 4, "fixed")
    assert over.matching.min_zncc == 0.7 and over.trust.keep_flagged is True
    # another mode: the fields the file left to the mode follow it, those it set stay
    accurate = shown("--mode", "accurate")
    assert (accurate.pipeline.mode, accurate.pipeline.window, accurate.pipeline.camera_model,
            accurate.pipeline.ba) == ("accurate", 2, "focal", "final")
    assert accurate.outliers.factor == 4.0 and accurate.motion_prior.explain_px == 1.5


def test_another_mode_over_a_resolved_config_takes_that_modes_defaults():
    recorded = Config.from_dict(Config().replace(bundle={"huber_px": 2.0}).to_dict())  # as report.json holds it
    paper = recorded.with_mode("paper").resolve()
    assert paper == Config(pipeline=PipelineConfig(mode="paper")).replace(bundle={"huber_px": 2.0}).resolve()
    kept = Config.from_dict(Config(pipeline=PipelineConfig(window=5)).to_dict()).with_mode("paper").resolve()
    assert kept.pipeline.window == 5 and kept.pipeline.camera_model == "free"


@pytest.fixture(scope="module")
def ring_files(box_scene, tmp_path_factory):
    from scene_helpers import scene_on_disk

    paths, calib = scene_on_disk(box_scene.prefix(4), tmp_path_factory.mktemp("ring"))
    return paths["images_txt"], calib


def test_a_report_json_replays_its_runs_configuration_and_cameras(ring_files, tmp_path, capsys):
    images, calib = ring_files
    settings = tmp_path / "run.toml"
    settings.write_text('[pipeline]\nmode = "paper"\n\n[features]\nmax_corners = 1200\n\n[outliers]\nmax_px = 3.5\n')
    first, again = tmp_path / "first", tmp_path / "again"
    assert main(["reconstruct", str(images), "--calib", str(calib), "--out", str(first), "--config", str(settings),
                 "--window", "2", "--quiet"]) == 0
    assert main(["reconstruct", str(images), "--calib", str(calib), "--out", str(again), "--quiet",
                 "--config", str(first / "report.json")]) == 0
    capsys.readouterr()
    report1, report2 = (json.loads((out / "report.json").read_text()) for out in (first, again))
    config = report1["config"]
    assert (config["pipeline"]["mode"], config["pipeline"]["window"], config["features"]["max_corners"],
            config["outliers"]["max_px"]) == ("paper", 2, 1200, 3.5)  # the file's and the option's
    assert report2["config"] == config
    assert Config.from_file(first / "report.json").resolve() == Config.from_toml(settings).replace(
        pipeline={"window": 2}).resolve()
    cams1, cams2 = (json.loads((out / "cameras.json").read_text())["images"] for out in (first, again))
    assert all(c["registered"] for c in cams1)
    assert [c["P"] for c in cams2] == [c["P"] for c in cams1]  # the same run, to the bit


def test_batch_takes_the_config_file_too(tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text('[trust]\nkeep_flaged = true\n')
    sequences = tmp_path / "sequences.txt"
    sequences.write_text("images calib.json out\n")
    assert main(["batch", str(sequences), "--config", str(path)]) == 2
    assert capsys.readouterr().err == (f"stereoseed: error: {path}: [trust] unknown key 'keep_flaged' "
                                       f"(did you mean keep_flagged?)\n")
