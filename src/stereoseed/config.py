"""All tunable parameters, gathered in :class:`Config`: one frozen dataclass per stage, each
defined beside the package it tunes (``features/config.py``, ``sfm/config.py``, ...) and
validated when it is built; :meth:`Config.resolve` fills the mode's defaults in, once.

A configuration file (docs/config.md) is TOML with one table per section of :class:`Config`
(``[matching]``, ``[pipeline]``, ...): :meth:`Config.from_toml`; a run's report.json holds the
resolved configuration it ran with: :meth:`Config.from_file` reads either,
:meth:`Config.from_dict` the dict itself, and :meth:`Config.to_toml` writes one back.

Every default states its source. "paper" is "Incremental Multi-view 3D Reconstruction Starting
from Two Images Taken by a Stereo Pair of Cameras" (see ../shared/paper.md); "LQ02" is
Lhuillier & Quan, "Match propagation for image-based modeling and rendering", PAMI 2002;
"HZ" is Hartley & Zisserman, Multiple View Geometry, 2nd ed.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from stereoseed.features.config import FeatureConfig
from stereoseed.matching.config import MatchingConfig, OrderingConfig, PropagationConfig
from stereoseed.estimators.config import TriangulationConfig, ResectionConfig, BundleConfig
from stereoseed.dense.config import DenseConfig, MeshConfig
from stereoseed.io.config import VideoConfig
from stereoseed.errors import StereoseedError
from stereoseed.output.config import ExportConfig
from stereoseed.sfm.config import (LoopClosureConfig, MotionPriorConfig, OutlierConfig, PairCheckConfig, PipelineConfig,
                                  QuasiDenseConfig, RegistrationConfig, TrackingConfig, TrustConfig)
from stereoseed.sfm.options import MapperOptions

__all__ = ["Config", "ResolvedConfig", "ConfigError", "NONE", "FeatureConfig", "MatchingConfig", "PropagationConfig", "TriangulationConfig",
           "ResectionConfig", "BundleConfig", "DenseConfig", "VideoConfig", "QuasiDenseConfig", "MotionPriorConfig",
           "TrackingConfig", "LoopClosureConfig", "PipelineConfig", "RegistrationConfig", "OutlierConfig",
           "PairCheckConfig", "ExportConfig", "TrustConfig", "OrderingConfig"]

# The fields a mode fills where they hold None, as (section, field, its ModeDefaults attribute):
# what Config.resolve fills in and Config.with_mode gives back to the new mode.
MODE_FIELDS = (("pipeline", "camera_model", "camera_model"), ("pipeline", "window", "window"),
               ("pipeline", "ba", "ba"), ("outliers", "factor", "outlier_factor"),
               ("motion_prior", "explain_px", "explain_px"))


@dataclass(frozen=True)
class Config:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    resection: ResectionConfig = field(default_factory=ResectionConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    propagation: PropagationConfig = field(default_factory=PropagationConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)  # stereoseed mesh, reconstruct --mesh
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
    ordering: OrderingConfig = field(default_factory=OrderingConfig)  # photos in any order (matching/ordering.py)
    export: ExportConfig = field(default_factory=ExportConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if not isinstance(getattr(self, f.name), f.default_factory):
                raise ValueError(f"Config.{f.name} must be a {f.default_factory.__name__}, "
                                 f"got {type(getattr(self, f.name)).__name__}")

    def resolve(self) -> "ResolvedConfig":
        """The configuration a run uses: the mode-dependent defaults (None) filled in, once (a
        :class:`ResolvedConfig` resolves to itself)."""
        sections = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        sections["pipeline"] = self.pipeline.resolved()  # its own fields, with their types
        defaults = sections["pipeline"].defaults
        for section, name, default in MODE_FIELDS:
            if getattr(sections[section], name) is None:
                sections[section] = dataclasses.replace(sections[section], **{name: getattr(defaults, default)})
        return ResolvedConfig(**sections)

    def mapper_options(self) -> MapperOptions:
        """The sections the mapper hands its components (:mod:`stereoseed.sfm.options`),
        resolved: built once at the top of a run."""
        resolved = self.resolve()
        return MapperOptions(**{f.name: getattr(resolved, f.name) for f in dataclasses.fields(MapperOptions)})

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

    def with_mode(self, mode: str) -> "Config":
        """Copy in another mode: a mode-dependent field holding the current mode's default (as a
        resolved configuration, or report.json, records it) takes the new mode's instead; a field
        set to anything else keeps its value."""
        old = self.pipeline.defaults
        sections = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        sections["pipeline"] = dataclasses.replace(self.pipeline, mode=mode)
        for section, name, default in MODE_FIELDS:
            if getattr(sections[section], name) == getattr(old, default):
                sections[section] = dataclasses.replace(sections[section], **{name: None})
        return Config(**sections)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "config") -> "Config":
        """A configuration from ``{section: {field: value}}``: what :meth:`to_dict` gives (so
        ``Config.from_dict(cfg.to_dict()).resolve() == cfg.resolve()``), report.json's
        ``"config"``, a parsed TOML file. Sections and fields left out keep their defaults; a
        field whose type allows None takes None or the string ``"none"``; an integer is taken for
        a float. Raises :class:`ConfigError`, one line naming ``where``, the section and the key:
        an unknown section or key, a value of the wrong type, or one the section refuses."""
        return _from_dict(data, where)

    @classmethod
    def from_toml(cls, path: str | Path) -> "Config":
        """The configuration of a TOML file, one table per section (docs/config.md)."""
        import tomllib

        path = Path(path)
        from stereoseed.io.nesting import MAX_NESTING, nesting_depth

        raw = _file_bytes(path, "a TOML configuration file (docs/config.md)")
        try:
            text = raw.decode("utf-8")
            if nesting_depth(text) > MAX_NESTING:  # tomllib recurses per level: RecursionError, a traceback
                raise ConfigError(f"{path}: nested more than {MAX_NESTING} levels deep; give a TOML configuration "
                                  f"file (docs/config.md: one table per section)")
            data = tomllib.loads(text)
        except UnicodeDecodeError:
            raise ConfigError(f"{path}: not UTF-8 text; give a TOML configuration file (docs/config.md)") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{path}: not valid TOML ({e})") from None
        return cls.from_dict(data, str(path))

    @classmethod
    def from_file(cls, path: str | Path) -> "Config":
        """A ``.json`` file: a run's report.json (its ``"config"``: the resolved configuration the
        run used) or a JSON object of sections; any other file: TOML (:meth:`from_toml`)."""
        path = Path(path)
        if path.suffix.lower() != ".json":
            return cls.from_toml(path)
        raw = _file_bytes(path, "a run's report.json or a TOML configuration file")
        try:
            data = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise ConfigError(f"{path}: not readable JSON; give a run's report.json or a TOML configuration "
                              f"file") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: not a JSON object; give a run's report.json or a TOML configuration file")
        config = data.get("config", data)
        return cls.from_dict(config, f"{path}" + (" (its config)" if "config" in data else ""))

    def to_toml(self) -> str:
        """The resolved configuration (:meth:`to_dict`) as TOML: every field, one table per
        section; :meth:`from_toml` reads it back to the same resolved configuration."""
        lines = ["# stereoseed configuration: every field, resolved (docs/config.md)"]
        for section, values in self.to_dict().items():
            lines += ["", f"[{section}]"] + [f"{key} = {_toml_value(value)}" for key, value in values.items()]
        return "\n".join(lines) + "\n"


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


NONE = "none"  # how a configuration file says None (TOML has no null): "the mode's", "off", "no test"


class ConfigError(StereoseedError, ValueError):
    """A configuration file or dict that cannot be taken: one line naming the file, the section
    and the key (a :class:`ValueError` too, as a field a dataclass refuses)."""


def _file_bytes(path: Path, what: str) -> bytes:
    """The bytes of a configuration file, or a ConfigError naming it and asking for ``what``."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: not found; give {what}") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot be read ({e.strerror or e})") from None


def _from_dict(data: Mapping[str, Any], where: str) -> Config:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: not a table of sections ([matching], [pipeline], ...; docs/config.md)")
    sections = {f.name: f.default_factory for f in dataclasses.fields(Config)}
    built = {}
    for name, values in data.items():
        if name not in sections:
            home = [s for s, cls in sections.items() if name in {f.name for f in dataclasses.fields(cls)}]
            hint = (f"; settings go in their section's table: [{home[0]}] {name} = ..." if home and
                    not isinstance(values, Mapping) else _did_you_mean(name, sections))
            raise ConfigError(f"{where}: unknown section {name!r}{hint}")
        if not isinstance(values, Mapping):
            raise ConfigError(f"{where}: {name} is not a table; write [{name}] and its settings below it")
        built[name] = _section(sections[name], name, values, where)
    return Config(**built)


def _section(cls: type, section: str, values: Mapping[str, Any], where: str) -> Any:
    """``cls`` (a section's dataclass) built from ``values``; each key checked, then the whole."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"{where}: [{section}] unknown key {key!r}{_did_you_mean(key, names)}")
        try:
            kwargs[key] = _typed(hints[key], value)
        except _WrongType as e:
            raise ConfigError(f"{where}: [{section}] {key} = {_shown(value)}: {e}") from None
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        # the key the section refuses on its own, else (a rule between fields) every key given
        alone = [k for k in kwargs if _refused(cls, k, kwargs[k])]
        named = f"{alone[0]} = {_shown(values[alone[0]])}" if alone else ", ".join(kwargs)
        raise ConfigError(f"{where}: [{section}] {named}: {e}") from None


def _refused(cls: type, key: str, value: Any) -> bool:
    try:
        cls(**{key: value})
    except (ValueError, TypeError):
        return True
    return False


# a whole number in a configuration file fits a C int: OpenCV's and the compiled kernels' integer
# parameters are C ints (a larger one overflows deep in a run), and no setting needs more
MAX_SETTING_INT = 2**31 - 1


class _WrongType(Exception):
    """A value that is not of its field's type; the message says what the field takes."""


def _typed(hint: Any, value: Any) -> Any:
    """``value`` (from TOML or JSON) as the type ``hint`` of a field: ints for floats become
    floats, arrays tuples, ``"none"`` (or null) None where the field allows it."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if value is None or (isinstance(value, str) and value == NONE):
            return None
        try:
            return _typed(inner[0], value)
        except _WrongType as e:
            raise _WrongType(f"{e}, or \"{NONE}\"") from None
    if typing.get_origin(hint) is tuple:
        if not isinstance(value, (list, tuple)):
            raise _WrongType(f"expected an array of {_kind(args[0], plural=True)}")
        try:
            return tuple(_typed(args[0], v) for v in value)
        except _WrongType:
            raise _WrongType(f"expected an array of {_kind(args[0], plural=True)}") from None
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            if abs(value) > MAX_SETTING_INT:
                raise _WrongType(f"expected a whole number within +-{MAX_SETTING_INT}")
            return int(value)
    elif hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):  # no setting means anything by NaN or infinity
                raise _WrongType("expected a finite number")
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return str(value)
    raise _WrongType(f"expected {_kind(hint)}")


def _kind(hint: Any, plural: bool = False) -> str:
    if plural:
        return {int: "whole numbers, e.g. [1, 2]", float: "numbers, e.g. [0.1, 0.2]"}.get(hint, str(hint))
    return {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}.get(hint, str(hint))


def _shown(value: Any) -> str:
    text = json.dumps(value, default=str) if not isinstance(value, bool) else str(value).lower()
    return text if len(text) <= 40 else text[:37] + "..."


def _did_you_mean(name: str, choices: Any) -> str:
    close = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean {close[0]}?)" if close else f"; the known ones: {', '.join(choices)}"


def _toml_value(value: Any) -> str:
    if value is None:
        return f'"{NONE}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return repr(value)
        return "nan" if math.isnan(value) else "inf" if value > 0 else "-inf"
    if isinstance(value, str):
        return json.dumps(str(value))
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML for {value!r}")
