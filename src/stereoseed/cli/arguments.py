"""Option values checked as argparse parses them: a bad one is a one-line usage error naming it."""
from __future__ import annotations

import argparse
from typing import Callable

__all__ = ["whole_number"]


def whole_number(low: int, high: int | None = None, what: str = "a whole number", note: str = "",
                 words: dict[str, int] | None = None) -> Callable[[str], int]:
    """The ``type=`` of an option taking a whole number in [low, high] (no upper bound when high is
    None): ``what`` names it when the text is not a number, ``note`` says why the bounds are what
    they are, ``words`` are texts that stand for a number (``{"auto": 0}``)."""
    bounds = f"at least {low}" if high is None else f"within {low}..{high}"
    if words:
        bounds += ", or " + " or ".join(words)
    bounds += f" ({note})" if note else ""

    def parse(text: str) -> int:
        if words and text in words:
            return words[text]
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {bounds}, got {value}")
        return value

    return parse
