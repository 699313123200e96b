"""threads: kernels' rows shared among the cores give the one-call results bit for bit."""
from __future__ import annotations

import os

import numpy as np
from stereoseed import threads
from stereoseed.config import MatchingConfig
from stereoseed.features.harris import extract_features
from stereoseed.matching.alignment import align_matches
from stereoseed.matching.containers import Matches
from stereoseed.matching.pair import candidate_config
from stereoseed.matching.zncc import candidate_pairs, match_zncc


def test_split_rows_cuts_contiguous_nearly_equal_chunks():
    assert threads.split_rows(10, 1, 3).tolist() == [0, 3, 7, 10]
    assert threads.split_rows(10, 6, 4).tolist() == [0, 10]  # too few rows for two threads
    assert threads.split_rows(0, 5, 4).tolist() == [0, 0]
    bounds = threads.split_rows(1001, 10, 8)
    assert len(bounds) == 9 and bounds[0] == 0 and bounds[-1] == 1001
    assert np.ptp(np.diff(bounds)) <= 1


def test_map_chunks_keeps_the_order():
    bounds = threads.split_rows(100, 1, 4)
    parts = threads.map_chunks(lambda a, b: list(range(a, b)), bounds)
    assert [i for part in parts for i in part] == list(range(100))


def _features(scene):
    return [extract_features(img) for img in scene.images[:2]]


def test_threaded_matching_is_the_one_call_matching(box_scene, monkeypatch):
    f1, f2 = _features(box_scene)
    cfg = candidate_config(MatchingConfig(), None)  # the recipe's first pass: many candidates
    monkeypatch.setattr(threads, "_chunks", 4)
    threaded = match_zncc(f1, f2, cfg)
    pairs = candidate_pairs(f1.points, f2.points, 100.0)
    aligned = align_matches(f1, f2, Matches(threaded.idx1, threaded.idx2, threaded.score), cfg)
    assert len(threaded) > 50
    monkeypatch.setattr(threads, "_chunks", 1)
    single = match_zncc(f1, f2, cfg)
    assert np.array_equal(threaded.idx1, single.idx1) and np.array_equal(threaded.idx2, single.idx2)
    assert np.array_equal(threaded.score, single.score)
    for a, b in zip(pairs, candidate_pairs(f1.points, f2.points, 100.0)):
        assert np.array_equal(a, b)
    again = align_matches(f1, f2, Matches(single.idx1, single.idx2, single.score), cfg)
    for name in ("x2", "affine", "zncc", "converged"):
        assert np.array_equal(getattr(aligned, name), getattr(again, name))


def test_a_forked_child_makes_its_own_pool():
    threads.map_chunks(lambda a, b: a, threads.split_rows(4, 1, 2))  # the parent's pool exists
    pid = os.fork()
    if pid == 0:  # the child: a pool inherited without its threads would never run the job
        try:
            out = threads.map_chunks(lambda a, b: b - a, threads.split_rows(4, 1, 2))
            os._exit(0 if out == [2, 2] else 1)
        except BaseException:
            os._exit(2)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_a_chunk_that_cuts_its_rows_again_runs_them_itself():
    """Nested calls run inline in the pool's threads: queued behind their caller they would
    never start (one pool thread on two cores)."""
    def outer(a, b):
        inner = threads.map_chunks(lambda c, d: d - c, threads.split_rows(b - a, 1, 2))
        return sum(inner)

    assert threads.map_chunks(outer, threads.split_rows(8, 1, 4)) == [2, 2, 2, 2]


def test_concatenated_chunks_and_mapped_items_keep_the_order(monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 3)
    a, b = threads.concat_chunks(lambda lo, hi: (np.arange(lo, hi), -np.arange(lo, hi)), 10, 2)
    assert a.tolist() == list(range(10)) and b.tolist() == [-i for i in range(10)]
    assert threads.map_items(lambda x: x * x, (1, 2, 3, 4)) == [1, 4, 9, 16]


def test_background_work_runs_in_its_own_thread_and_raises_where_its_result_is_taken(monkeypatch):
    import threading

    import pytest

    monkeypatch.setattr(threads, "_chunks", 2)
    with threads.in_background(lambda x: (x * 2, threading.current_thread().name), 21) as job:
        value, thread = job.result()
    assert value == 42 and thread.startswith("stereoseed-background")

    def fails():
        raise ValueError("bad input")

    with threads.in_background(fails) as job:
        with pytest.raises(ValueError, match="bad input"):
            job.result()


def test_background_work_on_one_core_runs_when_asked_and_not_otherwise(monkeypatch):
    monkeypatch.setattr(threads, "_chunks", 1)
    calls = []
    with threads.in_background(calls.append, 1) as job:
        assert calls == []  # nothing yet: one core, no thread
        job.result()
        job.result()  # as a Future's: the same value, not computed again
    assert calls == [1]
    with threads.in_background(calls.append, 2):
        pass  # not asked for: never computed
    assert calls == [1]
