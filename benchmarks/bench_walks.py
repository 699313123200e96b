"""`make bench` section `walks`: other walks through the real sets than section `real`'s (other
starts, other steps, backwards), with its figures (benchmarks/bench_real.py). No default was
chosen on them (the castle backwards and from 0010 showed the failures stop 43 fixed); a change is judged on
these together with the sets themselves: a threshold set on one walk shows here first.

    python benchmarks/bench_walks.py [WALK ...]      # prints the JSON; WALK e.g. "strechaCastleP19 backwards"
"""
from __future__ import annotations

import json
import sys

from bench_real import SETS, run_walk

_CASTLE, _FOUNTAIN = SETS["strechaCastleP19"], SETS["strechaFountainP11"]
_DINO, _TEMPLE, _DINO_SPARSE = SETS["dinoRing1-24/2"], SETS["templeSparseRing"], SETS["dinoSparseRing"]

WALKS = {
    "strechaCastleP19 backwards": _CASTLE._replace(reverse=True),
    "strechaCastleP19 every 2nd from 0001": _CASTLE._replace(step=2, start=1),
    "strechaCastleP19 from 0010": _CASTLE._replace(start=10),
    "strechaCastleP19 backwards from 0014": _CASTLE._replace(start=4, reverse=True),
    "strechaCastleP19 from 0008": _CASTLE._replace(start=8),
    "strechaFountainP11 backwards": _FOUNTAIN._replace(reverse=True),
    "strechaFountainP11 every 2nd": _FOUNTAIN._replace(step=2),
    "dinoRing1-24 every 2nd from 0002": _DINO._replace(step=2, start=1),
    "dinoRing1-24 every 3rd from 0002": _DINO._replace(step=3, start=1),
    "dinoRing1-24 every 3rd from 0003": _DINO._replace(step=3, start=2),
    "dinoRing1-24 every 4th from 0001": _DINO._replace(step=4),
    "dinoRing1-24 every 4th from 0002": _DINO._replace(step=4, start=1),
    "dinoRing1-24 every 4th from 0003": _DINO._replace(step=4, start=2),
    "templeSparseRing backwards": _TEMPLE._replace(reverse=True),
    "dinoSparseRing backwards": _DINO_SPARSE._replace(reverse=True),
    "dinoSparseRing backwards from its 13th": _DINO_SPARSE._replace(start=3, reverse=True),
    "dinoSparseRing backwards from its 12th": _DINO_SPARSE._replace(start=4, reverse=True),
}


def run(walks: list[str] | None = None) -> dict:
    return {name: run_walk(WALKS[name]) for name in (walks or WALKS)}


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1:] or None), indent=1, default=str))
