"""arrays: the sorted distinct values, the distinct pairs, the groups and the sort order, as NumPy's
np.unique and argsort give them."""
from __future__ import annotations

import numpy as np

from stereoseed.arrays import distinct_pair_firsts, sort_order, sorted_groups, unique


def test_unique_is_numpys():
    values = np.random.default_rng(0).integers(0, 50, 1000)
    np.testing.assert_array_equal(unique(values), np.unique(values))
    assert len(unique(np.zeros(0, np.int64))) == 0


def test_distinct_pair_firsts_counts_each_pair_once():
    first = np.array([3, 1, 3, 3, 0, 1])
    second = np.array([5, 2, 5, 7, 0, 2])
    assert distinct_pair_firsts(first, second).tolist() == [0, 1, 3, 3]
    huge = np.array([2**62, 2**62, 5])  # one key per pair would wrap: the lexicographic sort
    assert distinct_pair_firsts(huge, np.array([1, 4, 1])).tolist() == [5, 2**62, 2**62]


def test_sorted_groups_and_sort_order_are_numpys():
    rng = np.random.default_rng(0)
    # few distinct keys (ties kept in order), many, and keys too large to share an int64 with an index
    for keys in (rng.integers(0, 50, 1000), rng.integers(0, 2**40, 5000), rng.integers(0, 2**62, 300)):
        stable = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(sort_order(keys), stable)
        order, starts = sorted_groups(keys)
        np.testing.assert_array_equal(order, stable)
        _, first, counts = np.unique(keys[stable], return_index=True, return_counts=True)
        np.testing.assert_array_equal(starts, np.append(first, len(keys)))
        np.testing.assert_array_equal(np.diff(starts), counts)
    order, starts = sorted_groups(np.zeros(0, np.int64))
    assert len(order) == len(sort_order(np.zeros(0, np.int64))) == 0 and starts.tolist() == [0]


def test_sort_order_at_the_packing_limit():
    """Keys that just fit beside the index bits (the packed sort), one above (NumPy's argsort),
    negative ones (argsort too): each the stable order."""
    n = 100  # 7 index bits
    for top in (2**56 - 1, 2**56, -5):
        keys = np.random.default_rng(1).integers(0, 3, n) + top - 2
        np.testing.assert_array_equal(sort_order(keys), np.argsort(keys, kind="stable"))
        np.testing.assert_array_equal(sorted_groups(keys)[0], np.argsort(keys, kind="stable"))
