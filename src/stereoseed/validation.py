"""Checks of configuration fields: each raises ValueError naming the dataclass and the field, so
a wrong setting is refused where the configuration is built, not deep inside a run."""
from __future__ import annotations

import numbers
from typing import Any

__all__ = ["positive", "whole", "as_tuple", "in_range", "one_of"]


def positive(cfg: Any, *names: str) -> None:
    for name in names:
        value = getattr(cfg, name)
        if not value > 0:
            raise ValueError(f"{type(cfg).__name__}.{name} must be > 0, got {value!r}")


def whole(cfg: Any, *names: str, minimum: int = 1) -> None:
    for name in names:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
            raise ValueError(f"{type(cfg).__name__}.{name} must be a whole number >= {minimum}, got {value!r}")


def as_tuple(cfg: Any, name: str) -> None:
    """Sequences are stored as tuples: the frozen config stays hashable."""
    object.__setattr__(cfg, name, tuple(getattr(cfg, name)))


def in_range(cfg: Any, name: str, low: float, high: float) -> None:
    value = getattr(cfg, name)
    if not low <= value <= high:
        raise ValueError(f"{type(cfg).__name__}.{name} must be within [{low}, {high}], got {value!r}")


def one_of(cfg: Any, name: str, choices: tuple[str, ...], optional: bool = False) -> None:
    value = getattr(cfg, name)
    if value not in choices and not (optional and value is None):
        raise ValueError(f"{type(cfg).__name__}.{name} must be one of {', '.join(choices)}"
                         f"{' (or None)' if optional else ''}, got {value!r}")
