"""A model's start-up: the indexed points made once, in the k-d tree's leaf order, from the
stored leaf order (issue 31, "smaller models"). Checked against independent references: the
seam padding as it was written before (concatenated copies), scipy's cKDTree, numpy's
brute force and the ``tobytes`` digest."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rrtcolearn.data.store import digest, load_arrays, save_arrays
from rrtcolearn.errors import ArtefactError
from rrtcolearn.learn import LearnedFunctions
from rrtcolearn.learn.models import FUNCTIONS_FORMAT, _pad_periodic
from rrtcolearn.learn.neighbours import NeighbourIndex


def _reference_padding(X, periodic, scale, threshold):
    """The rows within reach of a seam repeated one turn over, as concatenated copies (the
    code before the leaf-ordered points, kept here as the reference)."""
    n = X.shape[1] // 2
    source = np.arange(len(X))
    for j, lo, hi in periodic:
        turn = hi - lo
        pad = threshold / scale[j]
        parts_x, parts_s = [X], [source]
        for near, shift in ((X[:, j] < lo + pad, turn), (X[:, j] >= hi - pad, -turn)):
            copy = X[near].copy()
            copy[:, j] += shift
            copy[:, n + j] += shift
            parts_x.append(copy)
            parts_s.append(source[near])
        X, source = np.concatenate(parts_x), np.concatenate(parts_s)
    return source, X


def test_seam_padding_is_the_concatenated_copies():
    """Two angles (an acrobot's), rows near both seams: the same rows in the same order,
    to the bit, as the concatenated copies."""
    rng = np.random.default_rng(0)
    X = rng.uniform(-np.pi, np.pi, size=(3000, 8))
    periodic = ((0, -np.pi, np.pi), (1, -np.pi, np.pi))
    scale = rng.uniform(0.5, 2.0, size=8)
    got_source, got = _pad_periodic(X, periodic, scale, 0.9)
    ref_source, ref = _reference_padding(X, periodic, scale, 0.9)
    assert len(ref) > 1.3 * len(X)  # copies across both seams, and copies of copies
    np.testing.assert_array_equal(got_source, ref_source)
    np.testing.assert_array_equal(got, ref)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.systems import make

    system = make("pendulum")  # an angle: the index holds copies across its seam
    data, _ = generate_data(system, 5, 600, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=0.8).fit(data, system)
    path = tmp_path_factory.mktemp("model") / "functions.npz"
    f.save(path)
    g, _ = LearnedFunctions.load(path)
    rng = np.random.default_rng(3)
    Q = np.hstack([data.x0[rng.choice(len(data), 200)], data.x1[rng.choice(len(data), 200)]])
    return f, g, path, Q


def test_loaded_index_is_the_padded_points_and_answers_as_brute_force(fitted):
    _, g, _, Q = fitted
    t = g.training_
    periodic = tuple((int(j), lo, hi) for j, lo, hi in t["periodic"])
    ref_source, ref = _reference_padding(t["inputs"], periodic, np.tile(t["input_scale"], 2),
                                         g.validity_threshold)
    ref = ref * np.tile(t["input_scale"], 2)  # the pendulum has no invariant coordinate
    points = g.cost_to_go_.index_.points
    assert len(ref) > len(t["inputs"])
    # the same (point, data row) pairs, in another order: the tree's leaf order
    a = np.column_stack([points, g.source_])
    b = np.column_stack([ref, ref_source])
    np.testing.assert_array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])
    # neighbours: cKDTree's distances to the bit, numpy's brute-force nearest row
    F = Q * g.input_scale_
    dist, idx = g.cost_to_go_.index_.query(F, 3)
    ref_dist, ref_idx = cKDTree(ref).query(F, 3)
    np.testing.assert_array_equal(dist, ref_dist)
    np.testing.assert_array_equal(points[idx], ref[ref_idx])
    brute = np.argmin(((F[:, None, :] - ref[None, :, :]) ** 2).sum(axis=2), axis=1)
    np.testing.assert_allclose(points[idx[:, 0]], ref[brute], rtol=0, atol=1e-12)
    # J is the saturated mean cost of those rows
    J, _, valid = g.query(Q)
    np.testing.assert_allclose(J, np.clip(t["cost"][ref_source[ref_idx]].mean(axis=1),
                                          *g.cost_bounds), rtol=1e-12)
    np.testing.assert_array_equal(valid, ref_dist.sum(axis=1) <= g.validity_threshold)


def test_loaded_model_answers_as_the_fitted_one(fitted):
    f, g, _, Q = fitted
    assert 0 < f.query(Q)[2].sum() < len(Q)  # valid and invalid queries both asked
    for a, b in zip(f.query(Q), g.query(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(f.query_valid(Q), g.query_valid(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(f.leaf_order_, g.leaf_order_)
    np.testing.assert_array_equal(f.cost_to_go_.index_.points, g.cost_to_go_.index_.points)


def _rewrite(path, out, change):
    arrays, meta = load_arrays(path, FUNCTIONS_FORMAT)
    change(arrays)
    save_arrays(out, FUNCTIONS_FORMAT, arrays,
                {k: v for k, v in meta.items()
                 if k not in ("format", "schema_version", "package_version", "sha256")})


def test_a_file_without_the_leaf_order_builds_the_same_model(fitted, tmp_path):
    """Model files from before the stored leaf order (no ``index.rows``) load, with the tree
    built again, to the same answers."""
    f, _, path, Q = fitted
    _rewrite(path, tmp_path / "old.npz", lambda a: a.pop("index.rows"))
    h, _ = LearnedFunctions.load(tmp_path / "old.npz")
    for a, b in zip(f.query(Q), h.query(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(f.leaf_order_, h.leaf_order_)


def test_a_leaf_order_that_is_no_permutation_is_refused(fitted, tmp_path):
    _, _, path, _ = fitted

    def spoil(arrays):
        rows = arrays["index.rows"].copy()
        rows[0] = rows[1]
        arrays["index.rows"] = rows

    _rewrite(path, tmp_path / "bad.npz", spoil)
    with pytest.raises(ArtefactError, match="permutation"):
        LearnedFunctions.load(tmp_path / "bad.npz")
    _rewrite(path, tmp_path / "short.npz",
             lambda a: a.__setitem__("index.rows", a["index.rows"][:-1]))
    with pytest.raises(ArtefactError, match="permutation"):
        LearnedFunctions.load(tmp_path / "short.npz")


def test_points_in_leaf_order_are_the_tree_itself():
    """An index given its points in leaf order (the identity order) keeps no second copy of
    them, answers as cKDTree does, and its bounds are the points' least and greatest."""
    points = np.random.default_rng(5).normal(size=(4000, 5))
    leaf = points[NeighbourIndex(points).rows]
    index = NeighbourIndex(leaf, np.arange(len(leaf)))
    assert index._tree[0] is index.points
    q = np.random.default_rng(6).normal(size=(50, 5))
    dist, idx = index.query(q, 4)
    ref_dist, ref_idx = cKDTree(leaf).query(q, 4)
    np.testing.assert_array_equal(dist, ref_dist)
    np.testing.assert_array_equal(idx, ref_idx)
    low, high = index.bounds
    np.testing.assert_array_equal(low, leaf.min(axis=0))
    np.testing.assert_array_equal(high, leaf.max(axis=0))


def test_digest_is_the_tobytes_digest():
    """The digest hashes each array's buffer: the bytes `tobytes` gives, for any dtype,
    layout and shape (files written before it check out)."""
    import hashlib

    arrays = {"a": np.arange(12.0).reshape(3, 4), "b": np.array(True),
              "c": np.zeros((0, 3)), "d": np.array("text"),
              "e": np.arange(12, dtype=np.int32)[::3], "f": np.array([1, 2], dtype=">i8"),
              "g": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
              "h": np.array([b"x", b"yz"])}
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(a.dtype.str.encode())
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    assert digest(arrays) == h.hexdigest()


def test_network_model_makes_the_knn_regressors_only_when_asked(fitted, tmp_path):
    """With the networks' J and U a loaded model makes no k-NN regressors (a plan never asks
    them); asked, they are the ones the fit made."""
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.systems import make

    _, _, _, Q = fitted
    system = make("pendulum")
    data, _ = generate_data(system, 5, 600, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=0.8, learner="mlp", mlp_hidden=(8,),
                         mlp_max_iter=3).fit(data, system)
    f.save(tmp_path / "mlp.npz")
    g, _ = LearnedFunctions.load(tmp_path / "mlp.npz")
    for a, b in zip(f.query(Q), g.query(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(f.query_valid(Q), g.query_valid(Q), strict=True):
        np.testing.assert_array_equal(a, b)
    assert g._knn is None
    F = Q * g.input_scale_
    np.testing.assert_array_equal(f.cost_to_go_.predict(F), g.cost_to_go_.predict(F))
    np.testing.assert_array_equal(f.steering_.predict(F), g.steering_.predict(F))
    assert g._knn is not None and g.cost_to_go_.index_ is g.validity_.index_


@pytest.fixture(scope="module")
def network_file(tmp_path_factory):
    """A small network model (the pendulum's data: seam copies in the index) and its file."""
    from rrtcolearn.data.generate import generate_data
    from rrtcolearn.systems import make

    system = make("pendulum")
    data, _ = generate_data(system, 5, 600, max_cost=2.0, max_state_distance=1.5)
    f = LearnedFunctions(validity_threshold=0.8, learner="mlp", mlp_hidden=(8,),
                         mlp_max_iter=3).fit(data, system)
    path = tmp_path_factory.mktemp("network") / "functions.npz"
    f.save(path)
    return f, path


def test_network_model_load_frees_the_training_arrays_before_the_index(network_file,
                                                                       monkeypatch):
    """Loading a network model frees the data's costs and steering targets before the
    index's points are made, and its inputs before the tree is built on them (issue 31:
    the load's peak memory holds the points and the tree, not the data as well); the
    loaded model holds none of them. Watched with weak references to the arrays the file
    gave."""
    import weakref

    from rrtcolearn.learn import models

    _, path = network_file
    refs, seen = {}, []
    real_training, real_points, real_index = (models._training_arrays,
                                              models._indexed_points, models.NeighbourIndex)

    def training_arrays(arrays):
        t = real_training(arrays)
        refs.update({k: weakref.ref(t[k]) for k in ("inputs", "cost", "targets")})
        return t

    def alive():
        return {k for k, r in refs.items() if r() is not None}

    def indexed_points(*args, **kwargs):
        seen.append(("points", alive()))
        return real_points(*args, **kwargs)

    def neighbour_index(*args, **kwargs):
        seen.append(("index", alive()))
        return real_index(*args, **kwargs)

    monkeypatch.setattr(models, "_training_arrays", training_arrays)
    monkeypatch.setattr(models, "_indexed_points", indexed_points)
    monkeypatch.setattr(models, "NeighbourIndex", neighbour_index)
    g, _ = LearnedFunctions.load(path)
    assert seen == [("points", {"inputs"}), ("index", set())]
    assert alive() == set() and g._training is None


def test_network_model_reads_its_training_arrays_again_when_asked(network_file, tmp_path):
    """The training arrays a loaded network model freed are read from its file when asked,
    bit for bit the fitted model's; saved again, the file holds the same arrays (the same
    digest). A file changed since the load is refused, not read."""
    import shutil

    f, path = network_file
    g, meta = LearnedFunctions.load(path)
    assert g._training is None
    assert g.max_duration_ == f.max_duration_
    assert sorted(g.training_) == sorted(f.training_)
    for k, v in f.training_.items():
        np.testing.assert_array_equal(g.training_[k], v)
        assert g.training_[k].dtype == v.dtype
    assert g.save(tmp_path / "again.npz") == meta["sha256"]

    changed = tmp_path / "changed.npz"
    shutil.copy(path, changed)
    h, _ = LearnedFunctions.load(changed)
    _rewrite(path, changed, lambda a: a.__setitem__("data.cost", a["data.cost"] * 2))
    with pytest.raises(ArtefactError, match="changed since the model was loaded"):
        h.training_  # noqa: B018


def test_knn_model_keeps_its_training_arrays(fitted):
    """The k-NN learner answers J and U from the data's costs and targets: nothing freed."""
    _, g, _, _ = fitted
    assert g._training is not None and g._released_from is None
