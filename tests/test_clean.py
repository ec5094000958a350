"""Alg. 3 cleaning: the compiled versions against a direct transcription of the paper."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rrtcolearn.data.clean import clean_data, clean_indices


def reference_alg3(X, cost, d, k_max, seed, block=1 << 18):
    """Alg. 3 transcribed with brute-force nearest neighbours and the same random stream."""
    rng = np.random.default_rng(seed)
    alive = list(range(len(X)))
    pos = {i: i for i in alive}
    k = 0
    u = rng.random(block)
    t = 0
    while k < k_max and len(alive) >= 2:
        if t == block:
            u, t = rng.random(block), 0
        idx = alive[int(u[t] * len(alive))]
        t += 1
        others = np.array([j for j in alive if j != idx])
        dist = np.linalg.norm(X[others] - X[idx], axis=1)
        order = np.lexsort((others, dist))
        nb, dnb = others[order[0]], dist[order[0]]
        if dnb < d:
            k = 0
            high = idx if cost[idx] > cost[nb] else nb
            p = pos.pop(high)
            last = alive.pop()
            if last != high:
                alive[p] = last
                pos[last] = p
        else:
            k += 1
    keep = np.zeros(len(X), dtype=bool)
    keep[alive] = True
    return keep


def test_matches_reference_transcription():
    rng = np.random.default_rng(5)
    X = rng.uniform(0, 1, (300, 4))
    X[100:200] = X[:100] + rng.normal(0, 0.02, (100, 4))  # many close pairs
    cost = rng.uniform(0, 1, 300)
    res = clean_indices(X, cost, d=0.08, k_max=200, seed=9, block=64)
    ref = reference_alg3(X, cost, 0.08, 200, 9, block=64)
    np.testing.assert_array_equal(res.keep, ref)
    assert 0 < res.keep.sum() < 300


def test_each_removal_keeps_the_cheaper_point_of_a_close_pair(small_dataset):
    d = small_dataset
    X = d.inputs
    cleaned, res = clean_data(d, d=0.05, k_max=2000, seed=1)
    assert len(res.removed) > 0
    gap = np.linalg.norm(X[res.removed] - X[res.removed_by], axis=1)
    assert np.all(gap < 0.05)
    assert np.all(d.cost[res.removed_by] <= d.cost[res.removed])
    assert len(cleaned) == len(d) - len(res.removed)
    assert not res.keep[res.removed].any()


def test_randomized_is_reproducible(small_dataset):
    a = clean_indices(small_dataset.inputs, small_dataset.cost, seed=4).keep
    b = clean_indices(small_dataset.inputs, small_dataset.cost, seed=4).keep
    np.testing.assert_array_equal(a, b)


def test_greedy_leaves_no_close_pair_and_covers_every_removed_point(small_dataset):
    d = small_dataset
    X = d.inputs
    res = clean_indices(X, d.cost, d=0.05, method="greedy")
    kept = X[res.keep]
    assert len(cKDTree(kept).query_pairs(0.05 - 1e-12)) == 0
    # every removed point has a kept point within d that is no costlier
    gap = np.linalg.norm(X[res.removed] - X[res.removed_by], axis=1)
    assert np.all(gap < 0.05)
    assert res.keep[res.removed_by].all()
    assert np.all(d.cost[res.removed_by] <= d.cost[res.removed])


def test_bad_parameters_are_refused(small_dataset):
    with pytest.raises(ValueError, match="positive"):
        clean_indices(small_dataset.inputs, small_dataset.cost, d=0.0)
    with pytest.raises(ValueError, match="unknown cleaning method"):
        clean_indices(small_dataset.inputs, small_dataset.cost, method="fast")


def test_kdtree_neighbour_lists_match_the_grid():
    """Inputs of many dimensions (a 6-state system's 12) are cleaned with k-d tree neighbour
    lists: the same lists, in the same order, as the grid's where both work."""
    from rrtcolearn.data import clean as C

    rng = np.random.default_rng(0)
    for dim, extent in ((4, 1.0), (8, 0.25)):
        pts = rng.uniform(0.0, extent, (5000, dim))
        g = C._Grid(pts, 0.05)
        cap = 8 * len(pts) + 16
        idx = np.empty(cap, dtype=np.int64)
        indptr, fill = C._neighbour_lists(g.points, g.table_keys, g.table_cells, g.cell_starts,
                                          g.lo, g.cell, g.dims, 0.05, idx, np.empty(cap))
        assert fill > 30
        kd_indptr, kd_idx = C._neighbour_lists_kdtree(g.points, 0.05)
        np.testing.assert_array_equal(kd_indptr, indptr)
        np.testing.assert_array_equal(kd_idx, idx[:fill])
    # 12 dimensions over a wide extent: the grid cannot number its cells, cleaning still runs
    pts = rng.uniform(-50.0, 50.0, (3000, 12))
    pts[1] = pts[0] + 0.01
    res = C.clean_indices(pts, rng.random(3000), d=0.05, method="greedy")
    assert res.keep.sum() == 2999
