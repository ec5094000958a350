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

A planar rotation (`System.planar_rotation` = (i, j, k): rotating the plane of the
invariant coordinates (x_i, x_j) and adding the angle to the heading x_k maps solutions to
solutions) removes the heading as well: the query is seen in x0's body frame,

    features(x0, x1) = (x0 without x_i, x_j, x_k and its other invariant coordinates,
                        x1 with (x1_i, x1_j) replaced by R(-x0_k) (x1_i - x0_i, x1_j - x0_j),
                        x1_k by x1_k - x0_k (wrapped into [-pi, pi) when x_k is an angle)
                        and its other invariant coordinates by their differences),

(2n - k - 1,). J and the duration are invariant under the rotation; the costate direction's
(i, j) components rotate with the plane, so U learns them in the body frame
(`QueryFeatures.steering_to_body`) and answers in the world frame
(`QueryFeatures.steering_to_world`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.systems.base import System

__all__ = ["QueryFeatures", "learning_geometry"]


@dataclass(frozen=True)
class QueryFeatures:
    """The map from query rows (x0, x1) to learning inputs for ``n_states`` coordinates of
    which ``invariant`` (sorted indices) are learned on their difference and, with
    ``rotation`` = (i, j, k) (i, j invariant), in x0's body frame (module docstring);
    ``heading_wraps``: x_k is an angle, its difference is wrapped into [-pi, pi)."""

    n_states: int
    invariant: tuple[int, ...] = ()
    rotation: tuple[int, ...] = ()
    heading_wraps: bool = False

    def __post_init__(self) -> None:
        inv = tuple(sorted(int(i) for i in self.invariant))
        if len(set(inv)) != len(inv) or any(not 0 <= i < self.n_states for i in inv):
            raise ValueError(f"invariant coordinates must be distinct indices in "
                             f"[0, {self.n_states}), got {self.invariant}")
        rot = tuple(int(i) for i in self.rotation)
        if rot and not (len(rot) == 3 and len(set(rot)) == 3 and rot[0] in inv
                        and rot[1] in inv and 0 <= rot[2] < self.n_states):
            raise ValueError(f"a planar rotation is (i, j, k) with i, j invariant and k "
                             f"another state index, got {self.rotation}")
        object.__setattr__(self, "invariant", inv)
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "heading_wraps", bool(self.heading_wraps) and bool(rot))

    @property
    def relative(self) -> tuple[int, ...]:
        """The coordinates x0 no longer shows: the invariant ones and the heading."""
        return tuple(sorted(set(self.invariant) | set(self.rotation[2:])))

    @property
    def columns(self) -> np.ndarray:
        """Indices into a query row (2n,) of the columns the features keep, in order."""
        n = self.n_states
        return np.array([j for j in range(n) if j not in self.relative]
                        + list(range(n, 2 * n)), dtype=np.int64)

    @property
    def width(self) -> int:
        """Number of features, 2n - k (one fewer with a rotation)."""
        return 2 * self.n_states - len(self.relative)

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Features (Q, width) of query rows X (Q, 2n); X itself without invariants."""
        X = np.asarray(X, dtype=np.float64)
        if not self.invariant:
            return X
        if X.ndim != 2 or X.shape[1] != 2 * self.n_states:
            raise ValueError(f"queries need shape (Q, {2 * self.n_states}), got {X.shape}")
        out = X[:, self.columns]
        n_kept = self.n_states - len(self.relative)
        for i in self.relative:
            out[:, n_kept + i] -= X[:, i]
        if self.rotation:
            i, j, k = self.rotation
            c, s = np.cos(X[:, k]), np.sin(X[:, k])
            dx, dy = out[:, n_kept + i].copy(), out[:, n_kept + j].copy()
            out[:, n_kept + i] = c * dx + s * dy
            out[:, n_kept + j] = c * dy - s * dx
            if self.heading_wraps:
                turn = out[:, n_kept + k]
                out[:, n_kept + k] = turn - 2.0 * np.pi * np.floor((turn + np.pi)
                                                                   / (2.0 * np.pi))
        return out

    def scale(self, state_scale: np.ndarray) -> np.ndarray:
        """Weights (width,) of the features from the state weights (n,): a difference
        x1_i - x0_i weighs as coordinate i does; with a rotation both body-frame position
        components weigh the mean of x_i's and x_j's weights (a distance that rotates)."""
        weights = np.asarray(state_scale, dtype=np.float64).copy()
        if self.rotation:
            i, j, _ = self.rotation
            weights[i] = weights[j] = 0.5 * (weights[i] + weights[j])
        return np.tile(weights, 2)[self.columns]

    def _turn_steering(self, X: np.ndarray, Y: np.ndarray, sign: float) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if not self.rotation:
            return Y
        i, j, k = self.rotation
        c, s = np.cos(X[:, k]), sign * np.sin(X[:, k])
        out = Y.copy()
        out[:, i] = c * Y[:, i] + s * Y[:, j]
        out[:, j] = c * Y[:, j] - s * Y[:, i]
        return out

    def steering_to_body(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """U's targets Y (Q, n+1) (the costate direction d, then the duration) of queries
        X (Q, 2n) with (d_i, d_j) turned by -x0_k into x0's body frame; Y itself without a
        rotation. Only the default direction parametrisation has d_i, d_j in columns i, j
        (`System.planar_rotation` is () otherwise)."""
        return self._turn_steering(X, Y, 1.0)

    def steering_to_world(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """The inverse of `steering_to_body`: U's body-frame answers Y turned by x0_k."""
        return self._turn_steering(X, Y, -1.0)


def learning_geometry(system: System, periodic: bool = True
                      ) -> tuple[QueryFeatures, tuple[tuple[int, float, float], ...]]:
    """The system's query features and the angle coordinates that wrap in the distance,
    ``(j, low, high)`` each (none when ``periodic`` is off). An invariant angle is learned on
    its difference, which a whole turn of both ends leaves unchanged: it needs no copies
    across the seam; so is a rotation's heading, whose difference is wrapped instead."""
    rotation = tuple(getattr(system, "planar_rotation", ()))
    features = QueryFeatures(system.n_states, tuple(system.invariant_coordinates), rotation,
                             bool(rotation) and rotation[2] in tuple(system.angle_dims))
    wrapped = tuple((int(j), float(system.state_low[j]), float(system.state_high[j]))
                    for j in system.angle_dims
                    if j not in features.relative) if periodic else ()
    return features, wrapped
