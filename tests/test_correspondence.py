"""The correspondence sources: the prefetching wrapper's speculative match."""
from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np

from stereoseed import threads
from stereoseed.config import Config
from stereoseed.correspondence import HarrisZncc, Prefetching


class _Counting(HarrisZncc):
    """HarrisZncc recording the thread of each match call."""

    def __init__(self, cfg):
        super().__init__(cfg)
        self.match_threads: list[str] = []

    def match(self, *args):
        self.match_threads.append(threading.current_thread().name)
        return super().match(*args)


def _same(m1, m2) -> bool:
    return all(np.array_equal(getattr(m1, k), getattr(m2, k)) for k in ("idx1", "idx2", "score"))


@contextmanager
def _view_0_final(scene):
    """Prefetching over the scene, told that view 0's interest points are final, then asked for
    view 1's: (the counting source, the wrapper, f0, f1, the image width)."""
    images = scene.images
    width = images[0].shape[1]
    source = _Counting(Config())
    with Prefetching(source, lambda i: images[i], len(images), first=0) as prefetching:
        f0 = prefetching.features(0, images[0])
        prefetching.expect_match(0, f0, width)
        yield source, prefetching, f0, prefetching.features(1, images[1]), width


def test_the_next_insertion_s_match_is_computed_ahead_and_is_the_direct_match(box_scene, monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 2)
    with _view_0_final(box_scene) as (source, prefetching, f0, f1, width):
        got = prefetching.match(0, 1, f0, f1, None, width)
    assert source.match_threads == ["stereoseed-matching_0"]  # computed ahead, once
    direct = HarrisZncc(Config()).match(0, 1, f0, f1, None, width)
    assert len(got) > 50 and _same(got, direct)


def test_a_match_it_did_not_foresee_is_computed_when_asked(box_scene, monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 2)
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    with _view_0_final(box_scene) as (source, prefetching, f0, f1, width):
        with_f = prefetching.match(0, 1, f0, f1, F, width)  # known F: not the speculated call
        again = prefetching.match(0, 1, f0, f1, None, width)  # the speculation was handed over once
    assert source.match_threads == ["stereoseed-matching_0", "MainThread", "MainThread"]
    assert _same(again, HarrisZncc(Config()).match(0, 1, f0, f1, None, width))
    assert _same(with_f, HarrisZncc(Config()).match(0, 1, f0, f1, F, width))


def test_one_core_matches_only_when_asked(box_scene, monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 1)
    with _view_0_final(box_scene) as (source, *_):
        assert source.match_threads == []
