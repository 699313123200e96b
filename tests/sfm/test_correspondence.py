"""The correspondence sources: the prefetching wrapper's speculative match."""
from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np

from stereoseed import threads
from stereoseed.config import Config
from stereoseed.sfm.correspondence import HarrisZncc, Prefetching


class _Counting(HarrisZncc):
    """HarrisZncc recording the thread of each match call."""

    def __init__(self, cfg):
        super().__init__(cfg.features, cfg.matching, cfg.tracking)
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
    direct = HarrisZncc.of(Config()).match(0, 1, f0, f1, None, width)
    assert len(got) > 50 and _same(got, direct)


def test_a_match_it_did_not_foresee_is_computed_when_asked(box_scene, monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 2)
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    with _view_0_final(box_scene) as (source, prefetching, f0, f1, width):
        with_f = prefetching.match(0, 1, f0, f1, F, width)  # known F: not the speculated call
        again = prefetching.match(0, 1, f0, f1, None, width)  # the speculation was handed over once
    assert source.match_threads == ["stereoseed-matching_0", "MainThread", "MainThread"]
    assert _same(again, HarrisZncc.of(Config()).match(0, 1, f0, f1, None, width))
    assert _same(with_f, HarrisZncc.of(Config()).match(0, 1, f0, f1, F, width))


def test_one_core_matches_only_when_asked(box_scene, monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 1)
    with _view_0_final(box_scene) as (source, *_):
        assert source.match_threads == []


class _HeldMatch(HarrisZncc):
    """HarrisZncc whose match waits (at most 5 s) until released, recording when it ran."""

    def __init__(self, cfg, events: list[str]):
        super().__init__(cfg.features, cfg.matching, cfg.tracking)
        self.events = events
        self.release = threading.Event()

    def match(self, *args):
        self.release.wait(5.0)
        self.events.append("match")
        return super().match(*args)


def test_tracking_runs_beside_the_speculative_match(box_scene, monkeypatch):
    # the mapper tracks the new view's points into the older views while the next match runs
    monkeypatch.setattr(threads, "_chunks", 2)
    images, events = box_scene.images, []
    width = images[0].shape[1]
    source = _HeldMatch(Config(), events)
    with Prefetching(source, lambda i: images[i], len(images), first=0) as prefetching:
        f0, f1 = prefetching.features(0, images[0]), prefetching.features(1, images[1])
        prefetching.expect_match(1, f1, width)  # view 1 with view 2, held
        m = HarrisZncc.of(Config()).match(0, 1, f0, f1, None, width)  # where view 1's points are in view 0
        idx, predicted = m.idx2, f0.points[m.idx1]
        xy, ok = prefetching.track(1, 0, f1, idx, f0, predicted, 2.0)
        events.append("tracked")
        source.release.set()
        prefetching.match(1, 2, f1, prefetching.features(2, images[2]), None, width)
    assert events == ["tracked", "match"]  # tracking did not wait for the held match
    xy_direct, ok_direct = HarrisZncc.of(Config()).track(1, 0, f1, idx, f0, predicted, 2.0)
    assert ok.sum() > 50 and np.array_equal(ok, ok_direct) and np.array_equal(xy, xy_direct)


def test_a_rig_s_next_station_match_is_computed_ahead(box_scene, monkeypatch):
    from stereoseed.sfm.modes import AccurateMode
    from stereoseed.sfm.rig import RigMode

    # the rig's views interleave the stations: a right image (odd) is matched next with the next
    # station's right image; a left one's interest points still grow, so none is computed for it
    assert [RigMode().next_match(k) for k in (2, 3, 4, 5)] == [None, 5, None, 7]
    assert AccurateMode().next_match(3) == 4
    monkeypatch.setattr(threads, "_chunks", 2)
    images = box_scene.images
    width = images[0].shape[1]
    source = _Counting(Config())
    with Prefetching(source, lambda i: images[i], len(images), first=1) as prefetching:
        f1 = prefetching.features(1, images[1])
        prefetching.expect_match(1, f1, width, 3)
        f2 = prefetching.features(2, images[2])
        f3 = prefetching.features(3, images[3])
        got = prefetching.match(1, 3, f1, f3, None, width)
        other = prefetching.match(1, 2, f1, f2, None, width)  # not the speculated pair: asked directly
    assert source.match_threads == ["stereoseed-matching_0", "MainThread"]
    assert _same(got, HarrisZncc.of(Config()).match(1, 3, f1, f3, None, width))
    assert _same(other, HarrisZncc.of(Config()).match(1, 2, f1, f2, None, width))
