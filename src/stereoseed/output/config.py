"""What the result folder and its exports keep."""
from __future__ import annotations

from dataclasses import dataclass

from stereoseed.validation import positive

__all__ = ["ExportConfig"]


@dataclass(frozen=True)
class ExportConfig:
    # exports leave out a point farther from the scene's median point than this many times the
    # cameras' median distance to it (nearly parallel rays put points metres away from the object)
    far_point_factor: float = 5.0

    def __post_init__(self) -> None:
        positive(self, "far_point_factor")
