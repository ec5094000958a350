"""k-NN learners with a fit/predict contract (paper Section 2 and Section 5).

Each learner stores hyper-parameters in ``__init__``, learns in ``fit(X, y)`` (returns self)
and keeps learned state in attributes ending in ``_``. ``predict_from_neighbours`` lets
`LearnedFunctions` answer J, U and V from a single neighbour query, which is what the planner
needs per iteration.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from rrtcolearn.data.store import load_arrays, save_arrays
from rrtcolearn.errors import ArtefactError
from rrtcolearn.learn.features import QueryFeatures, learning_geometry
from rrtcolearn.learn.neighbours import NeighbourIndex, check_permutation

if TYPE_CHECKING:
    from rrtcolearn.data.dataset import Dataset
    from rrtcolearn.learn.mlp import NeuralRegressor
    from rrtcolearn.systems.base import System

FUNCTIONS_FORMAT = "rrtcolearn.learned-functions"
#: Version of a model file's contents (its header's "version"). 2: J, U and V learn on
#: `QueryFeatures` (the invariant coordinates in ``data.invariant``). A file without it is
#: version 1, from before the features: it was fitted on the raw queries, which is what its
#: missing ``data.invariant`` (none) gives, so it loads and answers as it did. 3: a planar
#: rotation (``data.rotation``: i, j, k and whether the heading wraps; none before 3) puts the
#: queries in x0's body frame and U's targets with them (`QueryFeatures`).
FUNCTIONS_VERSION = 3
#: U's predictors from the neighbours: their mean (the paper's) or a local linear fit
STEERING_MODES = ("mean", "local_linear")
#: neighbours of U's local linear fit per feature, and its ridge (relative to the mean
#: squared distance of the neighbours): measured, docs/predictors.md
LOCAL_PER_FEATURE = 4
LOCAL_RIDGE = 0.01


class _KNNBase:
    def __init__(self, n_neighbors: int = 3):
        self.n_neighbors = n_neighbors

    def _fit_index(self, X: np.ndarray, index: NeighbourIndex | None) -> None:
        if self.n_neighbors < 1:
            raise ValueError("n_neighbors must be at least 1")
        if len(X) < self.n_neighbors:
            raise ValueError(f"need at least {self.n_neighbors} samples, got {len(X)}")
        self.index_ = index if index is not None else NeighbourIndex(X)

    def kneighbors(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices (Q, m) of the m nearest training inputs."""
        return self.index_.query(X, self.n_neighbors)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.predict_from_neighbours(*self.kneighbors(X))


# The k-NN answers for the few rows a planner iteration asks, compiled: numpy's fancy
# indexing and reductions cost tens of microseconds on such arrays. The sums run over the
# neighbours in order, as numpy's mean over that axis does, so the answers are the same
# numbers.


@numba.njit(cache=True)
def _mean_cost(cost, idx, low, high):
    """(Q,) the mean of ``cost`` over each row's neighbours ``idx`` (Q, m), clipped."""
    q, m = idx.shape
    out = np.empty(q)
    for r in range(q):
        s = cost[idx[r, 0]]
        for t in range(1, m):
            s += cost[idx[r, t]]
        out[r] = min(max(s / m, low), high)
    return out


@numba.njit(cache=True)
def _mean_steer(targets, cos_, sin_, idx):
    """The neighbours' means (over ``idx`` (Q, m)) of ``targets`` (Q, k) and of the circular
    columns' unit vectors ``cos_``, ``sin_`` (Q, c each)."""
    q, m = idx.shape
    out = np.empty((q, targets.shape[1]))
    cos_mean, sin_mean = np.empty((q, cos_.shape[1])), np.empty((q, cos_.shape[1]))
    for r in range(q):
        for j in range(targets.shape[1]):
            s = targets[idx[r, 0], j]
            for t in range(1, m):
                s += targets[idx[r, t], j]
            out[r, j] = s / m
        for j in range(cos_.shape[1]):
            sc, ss = cos_[idx[r, 0], j], sin_[idx[r, 0], j]
            for t in range(1, m):
                sc += cos_[idx[r, t], j]
                ss += sin_[idx[r, t], j]
            cos_mean[r, j], sin_mean[r, j] = sc / m, ss / m
    return out, cos_mean, sin_mean


def _local_linear(points, targets, circular, period, query, idx, ridge):
    """U at each query row as a ridge-regularised affine fit of its neighbours' targets on
    their features: for query q (scaled features, (d,)) and neighbours P (K, d) with
    targets Y (K, t), the intercept a of min |a + (P - q) B - Y|^2 + r |B|^2 with
    r = ``ridge`` * mean |P - q|^2, so the penalty scales with the neighbourhood. Circular
    columns are unwrapped around the nearest neighbour's value first (a line through angles
    must not jump a branch cut); the caller wraps them back."""
    q, K = idx.shape
    d = points.shape[1]
    out = np.empty((q, targets.shape[1]))
    A = np.empty((K, d + 1))
    A[:, 0] = 1.0
    reg = np.zeros(d + 1)
    for r in range(q):
        A[:, 1:] = points[idx[r]] - query[r]
        Y = targets[idx[r]].copy()
        if circular.any():
            ref = Y[0, circular]
            p = period[circular]
            Y[:, circular] = ref + np.mod(Y[:, circular] - ref + p / 2.0, p) - p / 2.0
        reg[1:] = ridge * float(np.sum(A[:, 1:] ** 2)) / K
        out[r] = np.linalg.solve(A.T @ A + np.diag(reg), A.T @ Y)[0]
    return out


@numba.njit(cache=True)
def _covered(X, lo, cell, dims, strides, flat):
    """(Q,) whether each query's cell (of size ``cell`` from ``lo``) lies in the grid of
    ``dims`` and is set in ``flat`` (the grid's bytes, ``strides`` per coordinate); a
    coordinate outside the grid, or NaN, is not covered."""
    out = np.zeros(X.shape[0], dtype=np.bool_)
    for r in range(X.shape[0]):
        offset = 0
        for j in range(X.shape[1]):
            c = np.floor((X[r, j] - lo[j]) / cell)
            if not (c >= 0.0 and c < dims[j]):
                break
            offset += np.int64(c) * strides[j]
        else:
            out[r] = flat[offset]
    return out


class CostToGoRegressor(_KNNBase):
    """J(x0, x1): mean cost of the m nearest training inputs, saturated to ``bounds``.

    The saturation at [1e-5, 1e5] is the paper's (Section 5): it keeps the learned distance
    within positive multiples of the Euclidean one.
    """

    def __init__(self, n_neighbors: int = 3, bounds: tuple[float, float] = (1e-5, 1e5)):
        super().__init__(n_neighbors)
        self.bounds = bounds

    def fit(self, X: np.ndarray, y: np.ndarray, index: NeighbourIndex | None = None):
        self._fit_index(X, index)
        self.cost_ = np.asarray(y, dtype=np.float64)
        return self

    def predict_from_neighbours(self, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return _mean_cost(self.cost_, np.ascontiguousarray(idx, dtype=np.int64),
                          *map(float, self.bounds))


class SteeringRegressor(_KNNBase):
    """U(x0, x1): costate parameters and duration, averaged over the m nearest inputs.

    Circular parameters (the pendulum's phi) are averaged on the circle: the mean direction of
    the unit vectors, mapped back into the parameter's domain, so neighbours on either side of
    the branch cut average to a nearby angle instead of the opposite one.
    """

    def __init__(self, n_neighbors: int = 3, circular: tuple[bool, ...] = (),
                 low: tuple[float, ...] = (), high: tuple[float, ...] = ()):
        super().__init__(n_neighbors)
        self.circular = circular
        self.low = low
        self.high = high

    def fit(self, X: np.ndarray, y: np.ndarray, index: NeighbourIndex | None = None):
        self._fit_index(X, index)
        y = np.asarray(y, dtype=np.float64)
        self.targets_ = y
        circ = np.zeros(y.shape[1], dtype=bool)
        circ[: len(self.circular)] = self.circular
        self.circular_ = circ
        self.low_ = np.asarray(self.low + (0.0,) * (y.shape[1] - len(self.low)))
        self.period_ = np.asarray(self.high + (0.0,) * (y.shape[1] - len(self.high))) - self.low_
        # unit-circle embedding of the circular columns, precomputed once
        angle = 2.0 * np.pi * (y[:, circ] - self.low_[circ]) / self.period_[circ]
        self.cos_, self.sin_ = np.cos(angle), np.sin(angle)
        return self

    def predict_from_neighbours(self, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        out, cos_mean, sin_mean = _mean_steer(self.targets_, self.cos_, self.sin_,
                                              np.ascontiguousarray(idx, dtype=np.int64))
        c = self.circular_
        if c.any():
            # numpy's arctan2 (vectorised, not libm's: they differ in the last bit)
            mean = np.arctan2(sin_mean, cos_mean)
            val = self.low_[c] + np.mod(mean, 2.0 * np.pi) * self.period_[c] / (2.0 * np.pi)
            # mod rounds a tiny negative angle up to 2 pi, which lands on high: wrap to low
            out[:, c] = np.where(val >= self.low_[c] + self.period_[c], self.low_[c], val)
        return out

    def predict_local(self, query: np.ndarray, idx: np.ndarray, ridge: float,
                      clip: bool = True) -> np.ndarray:
        """U at ``query`` (Q, d), scaled features as indexed, from a local linear regression
        over its neighbours ``idx`` (Q, K) (`_local_linear`): circular parameters wrapped
        into their range, the others and the duration clipped to the range the neighbours
        span (the fit must not extrapolate beyond what its data did: measured,
        docs/predictors.md)."""
        idx = np.ascontiguousarray(idx, dtype=np.int64)
        points = self.index_.points
        out = _local_linear(points, self.targets_, self.circular_, self.period_, query, idx,
                            ridge)
        c = self.circular_
        Y = self.targets_[idx]  # (Q, K, t)
        if clip:
            out[:, ~c] = np.clip(out[:, ~c], Y[:, :, ~c].min(axis=1),
                                 Y[:, :, ~c].max(axis=1))
        if c.any():
            low, period = self.low_[c], self.period_[c]
            val = low + np.mod(out[:, c] - low, period)
            out[:, c] = np.where(val >= low + period, low, val)
        return out


class ValidityClassifier(_KNNBase):
    """V(x0, x1): true when the summed distance to the m nearest inputs is <= ``threshold``.

    Queries far from every training input are where k-NN extrapolates badly (Section 5).
    """

    def __init__(self, n_neighbors: int = 3, threshold: float = 0.3):
        super().__init__(n_neighbors)
        self.threshold = threshold

    def fit(self, X: np.ndarray, y: np.ndarray | None = None,
            index: NeighbourIndex | None = None):
        self._fit_index(X, index)
        self._fit_coverage(np.asarray(X, dtype=np.float64))
        return self

    def _fit_coverage(self, X: np.ndarray) -> None:
        # A valid query has its nearest neighbour within threshold/m. With cells of that size,
        # such a neighbour lies in the query's cell or an adjacent one, so a one-cell dilation
        # of the occupied cells is a conservative, exact-to-the-result prefilter.
        cell = self.threshold / self.n_neighbors
        # X's least and greatest coordinates, from the index's root box (the same numbers
        # without two passes over X: a plan's start-up)
        low, high = self.index_.bounds
        lo = low - cell
        dims = np.floor((high - lo) / cell).astype(np.int64) + 2
        self.coverage_ = None
        if np.prod(dims.astype(np.float64)) > 5e7:  # too fine to store: skip the prefilter
            return
        occupied = np.zeros(tuple(dims), dtype=bool)
        occupied[tuple(np.floor((X - lo) / cell).astype(np.int64).T)] = True
        self.coverage_ = _dilate(occupied)
        self.coverage_lo_ = lo
        self.coverage_cell_ = cell
        self._coverage_flat = self.coverage_.ravel()
        self._coverage_strides = np.array(self.coverage_.strides, dtype=np.int64)
        self._coverage_dims = np.array(self.coverage_.shape, dtype=np.int64)

    def may_be_valid(self, X: np.ndarray) -> np.ndarray:
        """(Q,) False only where the query is certainly invalid; cheap, used to prune."""
        if self.coverage_ is None:
            return np.ones(len(X), dtype=bool)
        return _covered(np.ascontiguousarray(X, dtype=np.float64), self.coverage_lo_,
                        float(self.coverage_cell_), self._coverage_dims,
                        self._coverage_strides, self._coverage_flat)

    def predict_from_neighbours(self, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return dist.sum(axis=1) <= self.threshold


class _NeighbourAnswers:
    """J as the neighbours' average (the paper); U as their average too (``steering``
    "mean") or as a local linear regression over ``local`` neighbours ("local_linear")."""

    def __init__(self, cost_to_go: CostToGoRegressor, steering: SteeringRegressor,
                 mode: str = "mean", local: int = 0, ridge: float = 0.0,
                 scale: np.ndarray | None = None):
        self.cost_to_go, self.steering = cost_to_go, steering
        self.mode, self.local, self.ridge, self.scale = mode, local, ridge, scale

    def cost(self, X: np.ndarray, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return self.cost_to_go.predict_from_neighbours(dist, idx)

    def steer(self, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        if self.mode == "mean":
            return self.steering.predict_from_neighbours(None, idx)
        Xs = X * self.scale
        _, near = self.steering.index_.query(Xs, self.local)
        return self.steering.predict_local(Xs, near, self.ridge)


class _NetworkAnswers:
    """J and U from the networks on the query's features (the neighbours are not used)."""

    def __init__(self, networks: tuple[NeuralRegressor, NeuralRegressor],
                 bounds: tuple[float, float]):
        self.networks, self.bounds = networks, bounds

    def cost(self, X: np.ndarray, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return np.clip(self.networks[0].predict(X), *self.bounds)

    def steer(self, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return self.networks[1].predict(X)

    def cost_rows(self, X: np.ndarray) -> np.ndarray:
        """`cost` computed row by row (a row's J does not depend on the batch)."""
        return np.clip(self.networks[0].predict_plain(X), *self.bounds)


class LearnedFunctions:
    """J, U and V fitted on one dataset and answered from one shared neighbour query
    (scikit-learn's estimator contract: hyper-parameters in ``__init__``, ``fit`` returns
    self, learned state in attributes ending in ``_``; `save`/`load` without pickle).

    With ``learner = "mlp"``, J and U come from neural networks on the query instead of
    the neighbours' averages; V, and so which queries are answered at all, stays the k-NN
    classifier. ``periodic``: angle coordinates wrap in the distance (rows near the seam
    are indexed one turn over too). ``seed`` seeds the networks' training. ``steering``:
    U's k-NN predictor (`STEERING_MODES`, ``learn.steering``): the neighbours' mean (the
    paper's, the default) or a local linear fit (better on some systems, worse on others:
    docs/predictors.md).

    Every learner sees a query (x0, x1) through the system's `QueryFeatures`: along its
    invariant coordinates (`System.invariant_coordinates`) the difference x1_i - x0_i, so
    queries shifted along them get the same answers. The public queries take (x0, x1) rows.
    """

    def __init__(self, *, n_neighbors: int = 3,
                 cost_bounds: tuple[float, float] = (1e-5, 1e5),
                 validity_threshold: float = 0.3, learner: str = "knn", periodic: bool = True,
                 mlp_hidden: tuple[int, ...] = (64, 64, 64), mlp_max_iter: int = 200,
                 mlp_max_samples: int | None = 100_000, seed: int = 0,
                 steering: str = "mean"):
        self.n_neighbors = n_neighbors
        self.steering = steering
        self.cost_bounds = cost_bounds
        self.validity_threshold = validity_threshold
        self.learner = learner
        self.periodic = periodic
        self.mlp_hidden = mlp_hidden
        self.mlp_max_iter = mlp_max_iter
        self.mlp_max_samples = mlp_max_samples
        self.seed = seed

    def fit(self, data: Dataset, system: System) -> LearnedFunctions:
        """Fit on ``data``'s (x0, x1) -> (cost, steering parameters and duration), with the
        system's metric weights, angle coordinates and steering-parameter ranges."""
        if self.learner not in ("knn", "mlp"):
            raise ValueError(f"learner must be 'knn' or 'mlp', got {self.learner!r}")
        if self.steering not in STEERING_MODES:
            raise ValueError(f"steering must be one of {STEERING_MODES}, got "
                             f"{self.steering!r}")
        features, periodic = learning_geometry(system, self.periodic)
        self.training_ = {
            "inputs": np.asarray(data.inputs, dtype=np.float64),
            "cost": np.asarray(data.cost, dtype=np.float64),
            "targets": np.hstack([data.params, data.duration[:, None]]).astype(np.float64),
            "input_scale": np.asarray(system.metric_scale, dtype=np.float64),
            "circular": np.asarray(system.param_circular, dtype=bool).reshape(-1),
            "param_low": np.asarray(system.param_low, dtype=np.float64),
            "param_high": np.asarray(system.param_high, dtype=np.float64),
            "periodic": np.asarray(periodic, dtype=np.float64).reshape(-1, 3),
            "invariant": np.asarray(features.invariant, dtype=np.int64),
            "rotation": np.asarray(features.rotation + (int(features.heading_wraps),) * bool(
                features.rotation), dtype=np.int64)}
        self.max_duration_ = _max_duration(self.training_["targets"])
        self._fit_neighbours(*self._indexed(None))
        self.networks_ = None
        if self.learner == "mlp":
            self.networks_ = self._fit_networks()
        self._answers = self._neighbour_answers() \
            if self.networks_ is None else _NetworkAnswers(self.networks_, self.cost_bounds)
        return self

    def set_steering(self, steering: str) -> LearnedFunctions:
        """This model with U's k-NN predictor switched to ``steering`` (`STEERING_MODES`;
        the data and the index stay): for side-by-side measurements. Returns self."""
        if steering not in STEERING_MODES:
            raise ValueError(f"steering must be one of {STEERING_MODES}, got {steering!r}")
        self.steering = steering
        if self.networks_ is None:
            self._answers = self._neighbour_answers()
        return self

    def _neighbour_answers(self) -> _NeighbourAnswers:
        """The k-NN answers with this model's steering predictor: the local linear fit over
        `LOCAL_PER_FEATURE` neighbours per feature (a fit of 2n - k + 1 coefficients needs
        several times that many rows), at most every indexed point."""
        local = min(LOCAL_PER_FEATURE * self.features_.width, len(self.steering_.targets_))
        return _NeighbourAnswers(self.cost_to_go_, self.steering_, self.steering, local,
                                 LOCAL_RIDGE, self.input_scale_)

    def _indexed(self, rows: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The neighbour index's points (P, 2n - k), its leaf order (P,) and the data row
        of each point (P,), from the training inputs (the query features set on the way);
        ``rows``: the index's saved leaf order (`NeighbourIndex.rows`), which spares the
        tree's median searches. `_fit_neighbours` builds the index on them.

        The indexed points (the rows' scaled features, and their copies across angle seams)
        are made once, directly in the tree's leaf order, so that the tree holds no second
        copy of them: point i of the index is ``source_[i]``'s row, and every neighbour
        index the queries return is a position in that order (J, U and V answer as with
        the points in any other order: the same neighbours, the same sums)."""
        t = self.training_
        X = t["inputs"]
        n = X.shape[1] // 2
        rotation = tuple(int(i) for i in t.get("rotation", ()))
        self.features_ = QueryFeatures(n, tuple(int(i) for i in t.get("invariant", ())),
                                       rotation[:3], bool(rotation[3:] and rotation[3]))
        periodic = tuple((int(j), lo, hi) for j, lo, hi in t["periodic"])
        source, turns = _periodic_copies(X, periodic, np.tile(t["input_scale"], 2),
                                         self.validity_threshold)
        scale = self.features_.scale(t["input_scale"])
        if rows is None:  # a fit (or a file from before the saved order): build the tree
            rows = NeighbourIndex(_indexed_points(X, source, turns, periodic,
                                                  self.features_, scale)).rows
        # row numbers as int32 where they fit: half the memory of the three arrays of them
        rows = check_permutation(rows, len(source)).astype(_row_dtype(len(source)), copy=False)
        source = source[rows]
        self.input_scale_ = scale
        return _indexed_points(X, source, np.take(turns, rows, axis=0), periodic,
                               self.features_, scale), rows, source

    def _fit_neighbours(self, Xs: np.ndarray, rows: np.ndarray, source: np.ndarray) -> None:
        """The neighbour index on the points `_indexed` made, V on it, and J's and U's k-NN
        regressors for the k-NN learner."""
        index = NeighbourIndex(Xs, np.arange(len(Xs), dtype=rows.dtype))
        self.leaf_order_ = rows
        self.validity_ = ValidityClassifier(self.n_neighbors, self.validity_threshold).fit(
            Xs, None, index)
        self.source_ = source  # data row of each indexed point (padding repeats rows)
        # running share of the queries V accepted: where most are rejected, `query_valid`
        # first drops the rows whose nearest neighbour alone breaks the threshold (exact)
        self._accepted = 1.0
        # J's and U's k-NN regressors, on the same index: made now for the k-NN learner,
        # else when first asked for. The networks' plans never ask, and the regressors'
        # per-point copies of the costs and parameters would be the largest arrays after
        # the points themselves (98 MiB of an acrobot's default model)
        self._knn = None
        if self.learner == "knn":
            self._fit_knn()

    @property
    def training_(self) -> dict[str, np.ndarray]:
        """The arrays the model was fitted on and stores (``inputs`` (N, 2n), ``cost`` (N,),
        ``targets`` (N, k+1), the system's scales, ranges and symmetries). A network model
        loaded from a file does not hold them: its plans need only the index built from
        them, and they are the largest arrays after the index's points (a plan's peak
        memory, issue 31: docs/performance.md). Asked for (the k-NN regressors, `save`),
        they are read from that file again, which must still hold the arrays it was loaded
        from."""
        if self._training is None and self._released_from is not None:
            path, sha256 = self._released_from
            arrays, meta = load_arrays(path, FUNCTIONS_FORMAT)
            if meta.get("sha256") != sha256:
                raise ArtefactError(f"{path} changed since the model was loaded from it: "
                                    "load the model again")
            self._training = _training_arrays(arrays)
            self._released_from = None
        return self._training

    @training_.setter
    def training_(self, arrays: dict[str, np.ndarray]) -> None:
        self._training = arrays
        self._released_from = None

    def _fit_knn(self) -> None:
        """J's and U's k-NN regressors on V's index: the data rows' costs and steering
        targets copied to the indexed points (``source_``)."""
        t, index, source, m = self.training_, self.validity_.index_, self.source_, \
            self.n_neighbors
        circular = tuple(bool(c) for c in t["circular"])
        low, high = tuple(t["param_low"].tolist()), tuple(t["param_high"].tolist())
        self._knn = (
            CostToGoRegressor(m, self.cost_bounds).fit(index.points, t["cost"][source],
                                                       index),
            SteeringRegressor(m, circular, low, high).fit(
                index.points, self._steering_targets(source), index))

    def _steering_targets(self, source: np.ndarray) -> np.ndarray:
        """U's targets of data rows ``source``, in x0's body frame with a planar rotation
        (`QueryFeatures.steering_to_body`; the inputs are gathered only then)."""
        t = self.training_
        targets = np.take(t["targets"], source, axis=0)
        if not self.features_.rotation:
            return targets
        return self.features_.steering_to_body(np.take(t["inputs"], source, axis=0), targets)

    @property
    def cost_to_go_(self) -> CostToGoRegressor:
        """J's k-NN regressor (Section 5), on the shared index."""
        if self._knn is None:
            self._fit_knn()
        return self._knn[0]

    @property
    def steering_(self) -> SteeringRegressor:
        """U's k-NN regressor (Section 5), on the shared index."""
        if self._knn is None:
            self._fit_knn()
        return self._knn[1]

    def _fit_networks(self) -> tuple[NeuralRegressor, NeuralRegressor]:
        """The J network (on log cost) and the U network (circular parameters as angles),
        on the same data as the neighbours."""
        from rrtcolearn.learn.mlp import NeuralRegressor

        t, st = self.training_, self.steering_
        n_targets = t["targets"].shape[1]
        circ = tuple(bool(c) for c in st.circular_)
        low = tuple(float(v) for v in st.low_) + (0.0,) * (n_targets - len(st.low_))
        high = tuple(float(v) for v in st.low_ + st.period_)
        common = dict(hidden=tuple(self.mlp_hidden), max_iter=self.mlp_max_iter,
                      max_samples=self.mlp_max_samples)
        inputs = self.features_.transform(t["inputs"])
        j_net = NeuralRegressor(seed=self.seed, log_target=True, **common).fit(
            inputs, t["cost"])
        u_net = NeuralRegressor(seed=self.seed + 1, circular=circ, low=low, high=high,
                                **common).fit(
            inputs, self.features_.steering_to_body(t["inputs"], t["targets"]))
        return j_net, u_net

    def save(self, path: str | os.PathLike, meta: dict | None = None) -> str:
        """Write the fitted model (its training arrays and the networks' weights, no pickle)
        atomically; returns the arrays' digest. ``meta`` is stored in the header."""
        arrays = {f"data.{k}": v for k, v in self.training_.items()}
        # the neighbour index's leaf order: loading rebuilds the tree from it (0.04 s against
        # 0.2 s for the median searches on 500 000 points: a plan's start-up)
        arrays["index.rows"] = self.leaf_order_
        for p, net in zip("JU", self.networks_ or (), strict=False):
            arrays.update({f"{p}.{k}": v for k, v in net.to_arrays().items()})
        params = {"n_neighbors": self.n_neighbors, "cost_bounds": list(self.cost_bounds),
                  "validity_threshold": self.validity_threshold, "learner": self.learner,
                  "periodic": self.periodic, "mlp_hidden": list(self.mlp_hidden),
                  "mlp_max_iter": self.mlp_max_iter, "mlp_max_samples": self.mlp_max_samples,
                  "seed": self.seed}
        if self.steering != "mean":
            # only then: a file of the paper's predictor is what it was before the option
            # (an older rrtcolearn refuses one with it, as a file it cannot read)
            params["steering"] = self.steering
        return save_arrays(path, FUNCTIONS_FORMAT, arrays, {**(meta or {}), "params": params,
                                                            "version": FUNCTIONS_VERSION})

    @classmethod
    def load(cls, path: str | os.PathLike) -> tuple[LearnedFunctions, dict]:
        """A model written by `save` (the neighbour index rebuilt from its saved leaf order,
        the networks read back bit for bit) and the file's header; ArtefactError for anything
        that does not check out."""
        arrays, meta = load_arrays(path, FUNCTIONS_FORMAT)
        version = meta.get("version", 1)
        if version not in (1, 2, FUNCTIONS_VERSION):
            raise ArtefactError(f"{path} is a model file of version {version!r}; this "
                                f"rrtcolearn reads versions 1 to {FUNCTIONS_VERSION}: refit "
                                "it with `rrtcolearn fit`")
        for since, name in ((2, "invariant coordinates"), (3, "rotation")):
            key = "data." + name.split()[0]
            if version < since and key in arrays:
                raise ArtefactError(f"{path} is not a readable model file (version "
                                    f"{version} with {name})")
        try:
            params = dict(meta["params"])
            params["cost_bounds"] = tuple(params["cost_bounds"])
            params["mlp_hidden"] = tuple(params["mlp_hidden"])
            model = cls(**params)
            if model.steering not in STEERING_MODES:
                raise ValueError(f"steering {model.steering!r} is none of {STEERING_MODES}")
            model.networks_ = None
            if model.learner == "mlp":
                from rrtcolearn.learn.mlp import NeuralRegressor

                model.networks_ = tuple(NeuralRegressor.from_arrays(
                    {k[2:]: v for k, v in arrays.items() if k.startswith(f"{p}.")})
                    for p in "JU")
            rows = arrays.get("index.rows")  # (files before it: the tree is built)
            training = _training_arrays(arrays)
            del arrays  # from here on the training arrays are referenced by `training` only
            model.max_duration_ = _max_duration(training["targets"])
            if model.networks_ is not None:
                # the networks answer J and U: the index needs the inputs and the system's
                # constants, nothing reads the costs and steering targets, and the inputs
                # are not read once the index's points are made (`training_` reads them
                # all again if asked): each freed as soon as it is done with, so that the
                # load's peak holds the points and the tree, not the data as well
                training = {k: v for k, v in training.items() if k not in ("cost", "targets")}
            model.training_ = training
            del training
            indexed = model._indexed(rows)
            if model.networks_ is not None:
                model._training = None
                model._released_from = (Path(path), meta.get("sha256"))
            model._fit_neighbours(*indexed)
            del indexed
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtefactError(f"{path} is not a readable model file ({exc})") from None
        model._answers = model._neighbour_answers() \
            if model.networks_ is None else _NetworkAnswers(model.networks_,
                                                             model.cost_bounds)
        return model, meta

    def steer(self, X: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
        """U (Q, k+1) for queries X (Q, 2n) whose neighbour indices (Q, m) `query_valid`
        returned."""
        return self.features_.steering_to_world(
            X, self._answers.steer(self.features_.transform(X), neighbours))

    def query(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(J (Q,), U (Q, k+1), valid (Q,)) for queries X (Q, 2n)."""
        F = self.features_.transform(X)
        dist, idx = self.validity_.kneighbors(F * self.input_scale_)
        valid = self.validity_.predict_from_neighbours(dist, idx)
        steer = self.features_.steering_to_world(X, self._answers.steer(F, idx))
        return self._answers.cost(F, dist, idx), steer, valid

    def query_valid(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows of X (Q, 2n) that V accepts, with their J and their neighbour indices.

        A query is valid only if all its m neighbours lie within the validity threshold, so
        the neighbour search is bounded by it: invalid queries cost little. Returns
        (valid rows (V,), J (V,), neighbour indices (V, m)); U follows from `steer` for the
        row the caller picks.
        """
        F = self.features_.transform(X)
        Xs = F * self.input_scale_
        rows = np.flatnonzero(self.validity_.may_be_valid(Xs))
        threshold, m, index = self.validity_.threshold, self.n_neighbors, self.validity_.index_
        asked = len(X)
        if self._accepted < 0.5 and rows.size:
            # m distances summing to at most the threshold have the least of them within
            # threshold / m: that 1-NN search, bounded so tightly, is far cheaper than the
            # m-NN search for a query that fails (4-10x on 8-D queries), and it changes
            # no answer
            bound = threshold / m * (1.0 + 1e-9)  # a hair wide: rounding never drops one
            nearest, _ = index.query(Xs[rows], 1, max_distance=bound)
            rows = rows[nearest[:, 0] <= bound]
        dist, idx = index.query(Xs[rows], m, max_distance=threshold)
        ok = dist.sum(axis=1) <= threshold
        rows, dist, idx = rows[ok], dist[ok], idx[ok]
        if asked:
            self._accepted = 0.9 * self._accepted + 0.1 * rows.size / asked
        return rows, self._answers.cost(F[rows], dist, idx), idx


def best_valid(functions: LearnedFunctions, X: np.ndarray, offset: np.ndarray | None = None
               ) -> tuple[int, np.ndarray | None]:
    """The row of X (Q, 2n) that V accepts with the least J (the first such row among
    equal J) and its neighbour indices (m,) for `LearnedFunctions.steer`; (-1, None) when V
    accepts none. The row `query_valid`'s least J picks. ``offset`` (Q,): rank by J plus
    it instead (a parent's cost-to-come: RRT*'s choose-parent).

    With the networks' J it is found without V's answer for every row: J of every row
    the coverage prefilter keeps (row by row, `NeuralRegressor.predict_plain`), then V on
    the rows in order of J until one is valid (`NeighbourIndex.first_valid`), so V usually
    answers one or two rows instead of all. Those J values may differ from `query_valid`'s
    (numpy's batch products) in the last bits; the neighbours are not needed (None)."""
    answers = functions._answers
    if not isinstance(answers, _NetworkAnswers):
        rows, cost, idx = functions.query_valid(X)
        if rows.size == 0:
            return -1, None
        best = int(np.argmin(cost if offset is None else cost + offset[rows]))
        return int(rows[best]), idx[best]
    F = functions.features_.transform(X)
    Xs = F * functions.input_scale_
    rows = np.flatnonzero(functions.validity_.may_be_valid(Xs))
    if rows.size == 0:
        return -1, None
    cost = answers.cost_rows(F[rows])
    if offset is not None:
        cost = cost + offset[rows]
    order = rows[np.argsort(cost, kind="stable")]
    v = functions.validity_
    return v.index_.first_valid(Xs, order, v.n_neighbors, v.threshold), None


def _training_arrays(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The training arrays of a model file's arrays (``data.*``, without the prefix)."""
    return {k[5:]: v for k, v in arrays.items() if k.startswith("data.")}


def _max_duration(targets: np.ndarray) -> float:
    """The longest steering duration of the data (the targets' last column), 0 without
    data."""
    return float(targets[:, -1].max()) if len(targets) else 0.0


def _dilate(grid: np.ndarray) -> np.ndarray:
    """The cells of a boolean grid within one cell (in every coordinate) of a True cell:
    scipy.ndimage's maximum_filter(size=3, mode="constant", cval=False), as shifted ORs
    along each axis in turn (a tenth of its time, and no scipy.ndimage import at load)."""
    out = grid.copy()
    for axis in range(grid.ndim):
        before = out.copy()
        head = tuple(slice(1, None) if a == axis else slice(None) for a in range(grid.ndim))
        tail = tuple(slice(None, -1) if a == axis else slice(None) for a in range(grid.ndim))
        out[tail] |= before[head]
        out[head] |= before[tail]
    return out


def _row_dtype(n: int) -> type:
    """int32 for row numbers below 2**31, else int64."""
    return np.int32 if n < 2**31 else np.int64


def _periodic_copies(X: np.ndarray, periodic, scale: np.ndarray, threshold: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Which rows of X (N, 2n) are indexed once more one turn over each angle seam they lie
    within reach of: (source (P,), the row of X each indexed point repeats; turns (P, a)
    int8, the whole turns (+1, -1 or 0) it is shifted by along each of the ``a`` angles in
    ``periodic``), the rows of X first, in order, then each angle's copies of what came
    before (`_pad_periodic` makes the points)."""
    source = np.arange(len(X), dtype=_row_dtype(len(X) * 3 ** len(periodic)))
    turns = np.zeros((len(X), len(periodic)), dtype=np.int8)
    for a, (j, lo, hi) in enumerate(periodic):
        pad = threshold / scale[j]  # a farther copy can never be a valid neighbour
        column = X[source, j]  # (copies so far shift other angles, not this one)
        parts_s, parts_t = [source], [turns]
        for near, sign in ((column < lo + pad, 1), (column >= hi - pad, -1)):
            shifted = np.compress(near, turns, axis=0)  # (as turns[near], in less time)
            shifted[:, a] = sign
            parts_s.append(np.compress(near, source))
            parts_t.append(shifted)
        source, turns = np.concatenate(parts_s), np.concatenate(parts_t)
    return source, turns


@numba.njit(cache=True)
def _gather_turned(X, rows, turns, columns, turn, out):
    """``out[r] = X[rows[r]]`` with both ends of angle ``columns[a]`` moved by ``turns[r, a]``
    whole turns of ``turn[a]``: one compiled pass over the rows instead of numpy's gather,
    masks and in-place adds (a plan's start-up; the same sums)."""
    n = X.shape[1] // 2
    for r in range(rows.shape[0]):
        src = rows[r]
        for c in range(X.shape[1]):
            out[r, c] = X[src, c]
        for a in range(columns.shape[0]):
            if turns[r, a] != 0:
                shift = turns[r, a] * turn[a]
                out[r, columns[a]] += shift
                out[r, n + columns[a]] += shift
    return out


def _shifted_rows(X: np.ndarray, rows: np.ndarray, turns: np.ndarray, periodic,
                  out: np.ndarray | None = None) -> np.ndarray:
    """X[rows] (Q, 2n) with both ends of each angle moved by ``turns`` (Q, a) whole turns;
    written into ``out`` (at least Q rows) if given."""
    out = np.empty((len(rows), X.shape[1])) if out is None else out[:len(rows)]
    columns = np.array([int(j) for j, _, _ in periodic], dtype=np.int64)
    turn = np.array([hi - lo for _, lo, hi in periodic], dtype=np.float64)
    return _gather_turned(np.ascontiguousarray(X, dtype=np.float64), rows,
                          np.ascontiguousarray(turns, dtype=np.int8), columns, turn, out)


def _indexed_points(X: np.ndarray, source: np.ndarray, turns: np.ndarray, periodic,
                    features: QueryFeatures, scale: np.ndarray, chunk: int = 1 << 16
                    ) -> np.ndarray:
    """The index's points (P, 2n - k): the scaled features of rows ``source`` of X moved by
    ``turns`` (`_periodic_copies`), made a chunk of rows at a time into one buffer, so that
    a plan's start-up holds one array of them and no padded or unscaled copy."""
    out = np.empty((len(source), features.width))
    buf = np.empty((min(chunk, len(source)), X.shape[1]))
    for a in range(0, len(source), chunk):
        part = slice(a, a + chunk)
        rows = _shifted_rows(X, source[part], turns[part], periodic, buf)
        np.multiply(features.transform(rows), scale, out=out[part])
    return out


def _pad_periodic(X: np.ndarray, periodic, scale: np.ndarray, threshold: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(source rows, X with the rows within reach of a seam repeated one turn over)."""
    source, turns = _periodic_copies(X, periodic, scale, threshold)
    return source, _shifted_rows(X, source, turns, periodic)
