"""The kinds of flag a camera can carry (``View.flag_reason``, cameras.json's ``flag_reason``):
a reason starts with its kind, then says why with the figures, so a result read back from its
files gives the kind again (:func:`flag_kind`)."""
from __future__ import annotations

from enum import StrEnum

__all__ = ["FlagKind", "flag_kind"]


class FlagKind(StrEnum):
    AMBIGUOUS = "ambiguous: repeated structure"  # chosen on a margin over a rival a period away
    CONTRADICTED = "contradicted by the other cameras"  # its residuals after the final BA
    WEAK = "weak"  # too few observations of points two other cameras see
    UNCERTAIN = "uncertain"  # its position (or a zoom) measured too loosely


def flag_kind(reason: str) -> str:
    """The kind of a flag's ``reason`` (a :class:`FlagKind`'s value; else the reason up to its
    details)."""
    return next((kind.value for kind in FlagKind if reason.startswith(kind)), reason.split(" (")[0])
