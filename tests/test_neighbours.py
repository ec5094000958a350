"""The compiled k-d tree answers as scipy's cKDTree did, bit for bit."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rrtcolearn.learn.neighbours import NeighbourIndex


@pytest.mark.parametrize("dim", [1, 2, 4, 5, 8, 9])
def test_query_matches_scipy_bit_for_bit(dim):
    rng = np.random.default_rng(dim)
    points = rng.normal(size=(3000, dim)) * rng.uniform(0.1, 3.0, dim)
    scipy_tree = cKDTree(points)
    index = NeighbourIndex(points)
    queries = rng.normal(size=(500, dim)) * 2.0
    for k, bound in ((1, np.inf), (3, np.inf), (3, 0.7), (5, 1.5), (4, 0.0)):
        want_d, want_i = scipy_tree.query(queries, k=k, distance_upper_bound=bound)
        if k == 1:
            want_d, want_i = want_d[:, None], want_i[:, None]
        got_d, got_i = index.query(queries, k, max_distance=bound)
        assert np.array_equal(got_d, want_d) and np.array_equal(got_i, want_i)


@pytest.mark.parametrize("n", [0, 1, 2, 31, 33, 100])
def test_small_and_empty_sets(n):
    rng = np.random.default_rng(n)
    points = rng.normal(size=(n, 3))
    index = NeighbourIndex(points)
    d, i = index.query(rng.normal(size=(4, 3)), 3)
    assert d.shape == i.shape == (4, 3)
    got = min(n, 3)
    assert np.isfinite(d[:, :got]).all() and np.isinf(d[:, got:]).all()
    assert (i[:, got:] == n).all()


def test_first_valid_is_the_summed_distance_test():
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 1.0, size=(5000, 4))
    index = NeighbourIndex(points)
    queries = rng.uniform(-0.3, 1.3, size=(400, 4))
    threshold = 0.25
    d, _ = cKDTree(points).query(queries, k=3, distance_upper_bound=threshold)
    valid = d.sum(axis=1) <= threshold
    assert 0 < valid.sum() < len(valid)
    each = [index.first_valid(queries, np.array([r]), 3, threshold) == r
            for r in range(len(queries))]
    assert np.array_equal(np.array(each), valid)
    order = rng.permutation(len(queries))
    first = index.first_valid(queries, order, 3, threshold)
    assert first == order[np.flatnonzero(valid[order])[0]]
    assert index.first_valid(queries, order[~valid[order]], 3, threshold) == -1


@pytest.mark.parametrize("n", [0, 1, 31, 33, 5000])
def test_the_tree_rebuilt_from_its_leaf_order_is_the_same(n):
    """`NeighbourIndex(points, rows)` (a saved model's index) gives the arrays the median
    searches give, and so the same answers; a leaf order that is not a permutation is
    refused."""
    points = np.random.default_rng(n).normal(size=(n, 4))
    built = NeighbourIndex(points)
    again = NeighbourIndex(points, built.rows)
    for a, b in zip(built._tree, again._tree, strict=True):
        np.testing.assert_array_equal(a, b)
    if n > 1:
        q = np.random.default_rng(1).normal(size=(20, 4))
        for a, b in zip(built.query(q, 2), again.query(q, 2), strict=True):
            np.testing.assert_array_equal(a, b)
        bad = built.rows.copy()
        bad[0] = bad[1]
        with pytest.raises(ValueError, match="permutation"):
            NeighbourIndex(points, bad)


def _boxes_reference(data, n_inner, lo_of, hi_of):
    """Each node's bounding box written plainly: a leaf's least and greatest coordinates
    of its rows, an inner node's the least and greatest of its two children's."""
    box = np.empty((len(lo_of), 2, data.shape[1]))
    for node in range(len(lo_of) - 1, -1, -1):
        if node >= n_inner:
            rows = data[lo_of[node]:hi_of[node]]
            box[node, 0] = rows.min(axis=0) if len(rows) else np.inf
            box[node, 1] = rows.max(axis=0) if len(rows) else -np.inf
        else:
            a, b = 2 * node + 1, 2 * node + 2
            box[node, 0] = np.minimum(box[a, 0], box[b, 0])
            box[node, 1] = np.maximum(box[a, 1], box[b, 1])
    return box


@pytest.mark.parametrize("n, dim", [(1, 3), (33, 2), (1000, 7), (5000, 8)])
def test_node_boxes_are_the_plain_minima_and_maxima(n, dim):
    from rrtcolearn.learn.neighbours import _boxes, _build, _layout

    rng = np.random.default_rng(n)
    points = rng.normal(size=(n, dim))
    points[::7, 0] = 0.0  # repeated coordinates, signed zeros
    points[::11, -1] = -0.0
    data = _build(points, 32)[0]
    layout = _layout(n, 32)
    assert _boxes(data, *layout).tobytes() == _boxes_reference(data, *layout).tobytes()
