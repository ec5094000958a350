"""k-NN learners with a fit/predict contract (paper Section 2 and Section 5).

Each learner stores hyper-parameters in ``__init__``, learns in ``fit(X, y)`` (returns self)
and keeps learned state in attributes ending in ``_``. ``predict_from_neighbours`` lets
`LearnedFunctions` answer J, U and V from a single neighbour query, which is what the planner
needs per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import maximum_filter

from rrtcolearn.learn.neighbours import NeighbourIndex

if TYPE_CHECKING:
    from rrtcolearn.learn.mlp import NeuralRegressor


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
        return np.clip(self.cost_[idx].mean(axis=1), *self.bounds)


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
        out = self.targets_[idx].mean(axis=1)
        c = self.circular_
        if c.any():
            mean = np.arctan2(self.sin_[idx].mean(axis=1), self.cos_[idx].mean(axis=1))
            val = self.low_[c] + np.mod(mean, 2.0 * np.pi) * self.period_[c] / (2.0 * np.pi)
            # mod rounds a tiny negative angle up to 2 pi, which lands on high: wrap to low
            out[:, c] = np.where(val >= self.low_[c] + self.period_[c], self.low_[c], val)
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
        lo = X.min(axis=0) - cell
        dims = np.floor((X.max(axis=0) - lo) / cell).astype(np.int64) + 2
        self.coverage_ = None
        if np.prod(dims.astype(np.float64)) > 5e7:  # too fine to store: skip the prefilter
            return
        occupied = np.zeros(tuple(dims), dtype=bool)
        occupied[tuple(np.floor((X - lo) / cell).astype(np.int64).T)] = True
        self.coverage_ = maximum_filter(occupied, size=3, mode="constant", cval=False)
        self.coverage_lo_ = lo
        self.coverage_cell_ = cell
        self._coverage_flat = self.coverage_.ravel()
        self._coverage_strides = np.array(self.coverage_.strides, dtype=np.int64)
        self._coverage_dims = np.array(self.coverage_.shape, dtype=np.int64)

    def may_be_valid(self, X: np.ndarray) -> np.ndarray:
        """(Q,) False only where the query is certainly invalid; cheap, used to prune."""
        if self.coverage_ is None:
            return np.ones(len(X), dtype=bool)
        c = np.floor((X - self.coverage_lo_) / self.coverage_cell_).astype(np.int64)
        inside = ((c >= 0) & (c < self._coverage_dims)).all(axis=1)
        flat = np.where(inside, c @ self._coverage_strides, 0)
        return inside & self._coverage_flat[flat]

    def predict_from_neighbours(self, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
        return dist.sum(axis=1) <= self.threshold


@dataclass
class LearnedFunctions:
    """J, U and V fitted on one dataset and answered from one shared neighbour query.

    With ``networks`` (see `fit_networks`), J and U come from neural networks on the raw
    query instead of the neighbours' averages; V, and so which queries are answered at all,
    stays the k-NN classifier.
    """

    cost_to_go: CostToGoRegressor
    steering: SteeringRegressor
    validity: ValidityClassifier

    input_scale: np.ndarray | None = None  # (2n,) weights applied to every query
    source_: np.ndarray | None = None  # data row of each indexed point (padding repeats rows)
    networks: tuple[NeuralRegressor, NeuralRegressor] | None = None  # (J, U) networks
    # running share of the queries V accepted: where most are rejected, `query_valid` first
    # drops the rows whose nearest neighbour alone breaks the threshold (exact, cheap)
    _accepted: float = field(default=1.0, init=False, repr=False, compare=False)

    @classmethod
    def fit(cls, X: np.ndarray, cost: np.ndarray, steering_targets: np.ndarray, *,
            n_neighbors: int = 3, cost_bounds: tuple[float, float] = (1e-5, 1e5),
            validity_threshold: float = 0.3, circular: tuple[bool, ...] = (),
            low: tuple[float, ...] = (), high: tuple[float, ...] = (),
            input_scale: np.ndarray | None = None,
            periodic: tuple[tuple[int, float, float], ...] = ()) -> LearnedFunctions:
        """Fit on inputs X (N, 2n) = (x0, x1).

        ``input_scale`` (n,) weights the state coordinates in the distance (both halves).
        ``periodic`` lists angle coordinates as (j, low, high) with x0_j in [low, high) and
        high - low one turn: rows near either end are repeated one turn over (x0_j and x1_j
        shifted together, which leaves the problem unchanged), so a query near the seam finds
        the neighbours on its other side.
        """
        X = np.asarray(X, dtype=np.float64)
        n = X.shape[1] // 2
        scale = np.ones(2 * n) if input_scale is None else np.tile(
            np.asarray(input_scale, dtype=np.float64), 2)
        source = np.arange(len(X))
        if periodic and len(X):
            source, X = _pad_periodic(X, periodic, scale, validity_threshold)
        Xs = X * scale
        index = NeighbourIndex(Xs)
        cost = np.asarray(cost, dtype=np.float64)[source]
        steering_targets = np.asarray(steering_targets, dtype=np.float64)[source]
        return cls(
            CostToGoRegressor(n_neighbors, cost_bounds).fit(Xs, cost, index),
            SteeringRegressor(n_neighbors, circular, low, high).fit(Xs, steering_targets, index),
            ValidityClassifier(n_neighbors, validity_threshold).fit(Xs, None, index),
            None if input_scale is None else scale, source,
        )

    def fit_networks(self, X: np.ndarray, cost: np.ndarray, steering_targets: np.ndarray, *,
                     hidden: tuple[int, ...] = (64, 64, 64), max_iter: int = 200,
                     max_samples: int | None = 100_000, seed: int = 0) -> LearnedFunctions:
        """Train the J network (on log cost) and the U network (circular parameters as
        angles) on the same data as the neighbours; returns self."""
        from rrtcolearn.learn.mlp import NeuralRegressor

        st = self.steering
        n_targets = np.asarray(steering_targets).shape[1]
        circ = tuple(bool(c) for c in st.circular_)
        low = tuple(float(v) for v in st.low_) + (0.0,) * (n_targets - len(st.low_))
        high = tuple(float(v) for v in st.low_ + st.period_)
        common = dict(hidden=tuple(hidden), max_iter=max_iter, max_samples=max_samples)
        j_net = NeuralRegressor(seed=seed, log_target=True, **common).fit(X, cost)
        u_net = NeuralRegressor(seed=seed + 1, circular=circ, low=low, high=high,
                                **common).fit(X, steering_targets)
        self.networks = (j_net, u_net)
        return self

    @property
    def n_neighbors(self) -> int:
        return self.cost_to_go.n_neighbors

    def _network_cost(self, X: np.ndarray) -> np.ndarray:
        return np.clip(self.networks[0].predict(X), *self.cost_to_go.bounds)

    def steer(self, X: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
        """U (Q, k+1) for queries X (Q, 2n) whose neighbour indices (Q, m) `query_valid`
        returned."""
        if self.networks is not None:
            return self.networks[1].predict(np.asarray(X, dtype=np.float64))
        return self.steering.predict_from_neighbours(None, neighbours)

    def _scaled(self, X: np.ndarray) -> np.ndarray:
        return X if self.input_scale is None else np.asarray(X, dtype=np.float64) * \
            self.input_scale

    def query(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(J (Q,), U (Q, k+1), valid (Q,)) for queries X (Q, 2n)."""
        dist, idx = self.cost_to_go.kneighbors(self._scaled(X))
        valid = self.validity.predict_from_neighbours(dist, idx)
        if self.networks is not None:
            X = np.asarray(X, dtype=np.float64)
            return self._network_cost(X), self.networks[1].predict(X), valid
        return (
            self.cost_to_go.predict_from_neighbours(dist, idx),
            self.steering.predict_from_neighbours(dist, idx),
            valid,
        )

    def query_valid(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows of X (Q, 2n) that V accepts, with their J and their neighbour indices.

        A query is valid only if all its m neighbours lie within the validity threshold, so
        the neighbour search is bounded by it: invalid queries cost little. Returns
        (valid rows (V,), J (V,), neighbour indices (V, m)); U follows from `steer` for the
        row the caller picks.
        """
        Xs = self._scaled(X)
        rows = np.flatnonzero(self.validity.may_be_valid(Xs))
        threshold, m, index = self.validity.threshold, self.n_neighbors, self.cost_to_go.index_
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
        if self.networks is not None:
            return rows, self._network_cost(np.asarray(X, dtype=np.float64)[rows]), idx
        return rows, self.cost_to_go.predict_from_neighbours(dist, idx), idx


def _pad_periodic(X: np.ndarray, periodic, scale: np.ndarray, threshold: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(source rows, X with the rows within reach of a seam repeated one turn over)."""
    n = X.shape[1] // 2
    source = np.arange(len(X))
    for j, lo, hi in periodic:
        turn = hi - lo
        pad = threshold / scale[j]  # a farther copy can never be a valid neighbour
        parts_x, parts_s = [X], [source]
        for near, shift in ((X[:, j] < lo + pad, turn), (X[:, j] >= hi - pad, -turn)):
            copy = X[near].copy()
            copy[:, j] += shift
            copy[:, n + j] += shift
            parts_x.append(copy)
            parts_s.append(source[near])
        X, source = np.concatenate(parts_x), np.concatenate(parts_s)
    return source, X
