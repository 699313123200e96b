"""`make bench` section `walks`: other walks through the real sets than section `real`'s (other
starts, other steps, backwards), with its figures (benchmarks/bench_real.py). No default was
chosen on them (the castle backwards and from 0010 showed the failures stop 43 fixed); a change is judged on
these together with the sets themselves: a threshold set on one walk shows here first.

    python benchmarks/bench_walks.py [WALK ...]      # prints the JSON; WALK e.g. "strechaCastleP19 backwards"
"""
from __future__ import annotations

import json
import sys

from bench_real import Walk, run_walk

_CASTLE = ("strechaCastleP19", "strechaCastleP19_par.txt")
_FOUNTAIN = ("strechaFountainP11", "strechaFountainP11_par.txt")
_DINO = ("dinoRing1-24", "dinoRing1-24_par.txt")

WALKS = {
    "strechaCastleP19 backwards": Walk(*_CASTLE, reverse=True),
    "strechaCastleP19 every 2nd from 0001": Walk(*_CASTLE, step=2, start=1),
    "strechaCastleP19 from 0010": Walk(*_CASTLE, start=10),
    "strechaCastleP19 backwards from 0014": Walk(*_CASTLE, start=4, reverse=True),
    "strechaFountainP11 backwards": Walk(*_FOUNTAIN, reverse=True),
    "strechaFountainP11 every 2nd": Walk(*_FOUNTAIN, step=2),
    "dinoRing1-24 every 2nd from 0002": Walk(*_DINO, step=2, start=1),
    "dinoRing1-24 every 3rd from 0002": Walk(*_DINO, step=3, start=1),
    "dinoRing1-24 every 3rd from 0003": Walk(*_DINO, step=3, start=2),
    "dinoRing1-24 every 4th from 0001": Walk(*_DINO, step=4),
    "dinoRing1-24 every 4th from 0002": Walk(*_DINO, step=4, start=1),
    "dinoRing1-24 every 4th from 0003": Walk(*_DINO, step=4, start=2),
    "templeSparseRing backwards": Walk("templeSparseRing", "templeSR_par.txt", reverse=True),
    "dinoSparseRing backwards": Walk("dinoSparseRing", "dinoSR_par.txt", reverse=True),
    "dinoSparseRing backwards from its 13th": Walk("dinoSparseRing", "dinoSR_par.txt", start=3, reverse=True),
}


def run(walks: list[str] | None = None) -> dict:
    return {name: run_walk(WALKS[name]) for name in (walks or WALKS)}


if __name__ == "__main__":
    print(json.dumps(run(sys.argv[1:] or None), indent=1, default=str))
