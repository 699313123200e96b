"""arrays: the sorted distinct values and the distinct pairs, as NumPy's np.unique gives them."""
from __future__ import annotations

import numpy as np

from stereoseed.arrays import distinct_pair_firsts, unique


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
