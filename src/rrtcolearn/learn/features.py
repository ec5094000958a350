"""The learning inputs of a query (x0, x1): the one place the learners' features are made.

J, U and V answer a query row (x0, x1) (2n,). Along an invariant coordinate i
(`System.invariant_coordinates`: nothing of the optimal control problem depends on x_i) the
answers depend on x1_i - x0_i alone, so the learners see

    features(x0, x1) = (x0 without its invariant coordinates,
                        x1 with x1_i replaced by x1_i - x0_i for each invariant i),

(2n - k,) for k invariant coordinates: a shifted query has the same features, and data from
anywhere along the coordinate serve every query. Without invariant coordinates the features
are the query itself (the same array), so such a model is the paper's. The fit, every
prediction (k-NN and networks), V's coverage grid, the validity threshold's derivation and a
loaded model all take their inputs from `QueryFeatures.transform`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.systems.base import System

__all__ = ["QueryFeatures", "learning_geometry"]


@dataclass(frozen=True)
class QueryFeatures:
    """The map from query rows (x0, x1) to learning inputs for ``n_states`` coordinates of
    which ``invariant`` (sorted indices) are learned on their difference."""

    n_states: int
    invariant: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        inv = tuple(sorted(int(i) for i in self.invariant))
        if len(set(inv)) != len(inv) or any(not 0 <= i < self.n_states for i in inv):
            raise ValueError(f"invariant coordinates must be distinct indices in "
                             f"[0, {self.n_states}), got {self.invariant}")
        object.__setattr__(self, "invariant", inv)

    @property
    def columns(self) -> np.ndarray:
        """Indices into a query row (2n,) of the columns the features keep, in order."""
        n = self.n_states
        return np.array([j for j in range(n) if j not in self.invariant]
                        + list(range(n, 2 * n)), dtype=np.int64)

    @property
    def width(self) -> int:
        """Number of features, 2n - k."""
        return 2 * self.n_states - len(self.invariant)

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Features (Q, 2n - k) of query rows X (Q, 2n); X itself without invariants."""
        X = np.asarray(X, dtype=np.float64)
        if not self.invariant:
            return X
        if X.ndim != 2 or X.shape[1] != 2 * self.n_states:
            raise ValueError(f"queries need shape (Q, {2 * self.n_states}), got {X.shape}")
        out = X[:, self.columns]
        n_kept = self.n_states - len(self.invariant)
        for i in self.invariant:
            out[:, n_kept + i] -= X[:, i]
        return out

    def scale(self, state_scale: np.ndarray) -> np.ndarray:
        """Weights (2n - k,) of the features from the state weights (n,): a difference
        x1_i - x0_i weighs as coordinate i does."""
        return np.tile(np.asarray(state_scale, dtype=np.float64), 2)[self.columns]


def learning_geometry(system: System, periodic: bool = True
                      ) -> tuple[QueryFeatures, tuple[tuple[int, float, float], ...]]:
    """The system's query features and the angle coordinates that wrap in the distance,
    ``(j, low, high)`` each (none when ``periodic`` is off). An invariant angle is learned on
    its difference, which a whole turn of both ends leaves unchanged: it needs no copies
    across the seam."""
    features = QueryFeatures(system.n_states, tuple(system.invariant_coordinates))
    wrapped = tuple((int(j), float(system.state_low[j]), float(system.state_high[j]))
                    for j in system.angle_dims
                    if j not in features.invariant) if periodic else ()
    return features, wrapped
