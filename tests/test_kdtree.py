"""registration.kdtree.KDTree: pykdtree with scipy cKDTree's answers and conventions.

On points in general position (random floats: no two distances tie) both trees return the
exact nearest neighbours, so the indices must be equal and the distances bit for bit (both
take the square root of the same float64 sum of three squared differences).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from torchslam.registration.kdtree import KDTree, _runtime


@pytest.fixture(scope="module")
def clouds():
    rng = np.random.default_rng(7)
    data = rng.normal(size=(3000, 3)) * [5.0, 2.0, 0.5]
    query = np.concatenate(
        [data[:500] + rng.normal(size=(500, 3)) * 0.01, rng.normal(size=(500, 3)) * 8]
    )
    return data, query


@pytest.mark.parametrize("k", [1, 2, 10])
@pytest.mark.parametrize("bound", [np.inf, 0.3, 1e-9])
def test_answers_equal_ckdtree(clouds, k, bound):
    data, query = clouds
    expected = cKDTree(data).query(query, k=k, distance_upper_bound=bound)
    got = KDTree(data).query(query, k=k, distance_upper_bound=bound)
    assert got[0].dtype == np.float64 and got[1].dtype == np.int64
    assert got[0].shape == expected[0].shape and got[1].shape == expected[1].shape
    np.testing.assert_array_equal(got[1], expected[1])  # misses: index N, as scipy
    np.testing.assert_array_equal(got[0], expected[0])  # bit for bit, inf where missing


def test_small_empty_and_threads(clouds):
    data, query = clouds
    # fewer points than k: the missing neighbours are (inf, N), as scipy pads them
    d, i = KDTree(data[:3]).query(query[:4], k=5)
    e = cKDTree(data[:3]).query(query[:4], k=5)
    np.testing.assert_array_equal(d, e[0])
    np.testing.assert_array_equal(i, e[1])
    # an empty tree (pykdtree refuses to build one) misses everything; an empty query is empty
    d, i = KDTree(np.zeros((0, 3))).query(query[:4], k=2)
    assert np.isinf(d).all() and (i == 0).all() and d.shape == (4, 2)
    d, i = KDTree(data).query(np.zeros((0, 3)))
    assert d.shape == (0,) and i.shape == (0,)
    # the same answers on any number of threads; torch's count unchanged, and the OpenMP
    # runtime's: restored when shared, pykdtree's own left at the last query's count
    threads = torch.get_num_threads()
    found = _runtime()
    before = None if found is None else [lib["num_threads"] for lib in found[0].info()]
    one = KDTree(data).query(query, k=3, workers=1)
    two = KDTree(data).query(query, k=3, workers=2)
    np.testing.assert_array_equal(one[0], two[0])
    np.testing.assert_array_equal(one[1], two[1])
    assert torch.get_num_threads() == threads
    if found is not None:
        runtime, own = found
        after = [lib["num_threads"] for lib in runtime.info()]
        assert after == ([2] * len(after) if own else before)
        KDTree(data).query(query[:5], workers=1)
        assert not own or [lib["num_threads"] for lib in runtime.info()] == [1] * len(after)
