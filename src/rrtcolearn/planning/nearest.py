"""Nearest tree nodes for the planner: a k-d tree over the older nodes plus the newest ones.

OMPL's planners keep their nodes in a `NearestNeighbors` structure so that an iteration's cost
does not grow with the tree; this is ours. The metric is the weighted Euclidean distance of
the learners (`System.metric_scale`) in plain state coordinates, the one the planner has
always ranked its candidates by. scipy's k-d tree cannot take insertions, so the index keeps
the nodes added since its last build in a small buffer that is searched by brute force, and
rebuilds when the buffer holds ``rebuild_every`` nodes: the amortised build cost per node is
O(log n) and a query costs O(log n + rebuild_every). Up to `_SCAN_ALL` nodes a compiled scan
of all of them is cheaper than scipy's query (its per-call overhead: measured 21.7 against
27.1 us at 1000 4-D nodes, 38.6 against 26.1 us at 2000).
"""

from __future__ import annotations

import numba
import numpy as np

# below this many points a compiled scan of all of them is cheaper than the k-d tree's query
# (scipy's per-call overhead); the answers are the same either way (see `NodeIndex`)
_SCAN_ALL = 1024


@numba.njit(cache=True)
def _sqdists(points, idx, lo, hi, q, period):
    """Squared distances to ``q`` of ``points[idx]`` followed by ``points[lo:hi]``, with the
    coordinates of positive ``period`` compared the short way round: (indices, distances)."""
    m = idx.size + hi - lo
    out_i = np.empty(m, np.int64)
    out_d = np.empty(m)
    n = q.size
    for r in range(m):
        i = idx[r] if r < idx.size else lo + r - idx.size
        acc = 0.0
        for j in range(n):
            d = points[i, j] - q[j]
            p = period[j]
            if p > 0.0:
                d = np.mod(d + 0.5 * p, p) - 0.5 * p
            acc += d * d
        out_i[r] = i
        out_d[r] = acc
    return out_i, out_d


@numba.njit(cache=True)
def _least(idx, d2):
    """The index of least distance, the least index among equal distances."""
    best = 0
    for r in range(1, idx.size):
        if d2[r] < d2[best] or (d2[r] == d2[best] and idx[r] < idx[best]):
            best = r
    return idx[best]


_NONE = np.empty(0, np.int64)


class NodeIndex:
    """k nearest of the added points (n,) under ``|weight * (x - y)|``.

    With ``angle_low`` (n,) (NaN for coordinates that are not angles) angle coordinates are
    compared modulo a turn: points are stored wrapped into [low, low + 2 pi) and the k-d tree
    is periodic there. Results are ordered by (distance, index), so they do not depend on how
    the points are split between the k-d tree and the buffer.
    """

    def __init__(self, weight: np.ndarray, angle_low: np.ndarray | None = None,
                 rebuild_every: int = 256):
        self.weight = np.asarray(weight, dtype=np.float64)
        n = len(self.weight)
        low = np.full(n, np.nan) if angle_low is None else np.asarray(angle_low, float)
        self._angles = np.flatnonzero(np.isfinite(low))
        self._low = np.where(np.isfinite(low), low, 0.0) * self.weight
        self._period = np.where(np.isfinite(low), 2.0 * np.pi * self.weight, 0.0)
        self.rebuild_every = int(rebuild_every)
        self._points = np.empty((256, len(self.weight)))
        self._size = 0
        self._indexed = 0  # points [0, _indexed) are in the k-d tree
        self._tree = None  # scipy's cKDTree, once there are enough nodes

    def __len__(self) -> int:
        return self._size

    def add(self, x: np.ndarray) -> None:
        if self._size == self._points.shape[0]:
            self._points = np.concatenate([self._points, np.empty_like(self._points)])
        self._points[self._size] = self._wrapped(np.asarray(x, dtype=np.float64))
        self._size += 1
        if self._size - self._indexed >= self.rebuild_every:
            self._rebuild()

    def reserve(self, k: int) -> np.ndarray:
        """The points array with room for ``k`` more points, for a compiled caller to write
        them in stored coordinates (`_wrapped`) before `commit`."""
        while self._points.shape[0] < self._size + k:
            self._points = np.concatenate([self._points, np.empty_like(self._points)])
        return self._points

    def commit(self, size: int) -> None:
        """Take the points written into `reserve`'s array up to ``size`` as added."""
        self._size = size
        if self._size - self._indexed >= self.rebuild_every:
            self._rebuild()

    def set(self, i: int, x: np.ndarray) -> None:
        """Replace the point ``i`` not yet committed (`reserve`)."""
        self._points[i] = self._wrapped(np.asarray(x, dtype=np.float64))

    def kernel_rows(self) -> np.ndarray:
        """(4, n): the weights, the weighted angle lows, the periods and 1.0 at the angle
        coordinates: how a compiled caller (`integrate.explore_jit`) stores and compares
        points as this index does."""
        n = len(self.weight)
        return np.array([self.weight, self._low, self._period,
                         np.isin(np.arange(n), self._angles)], dtype=np.float64)

    def _rebuild(self) -> None:
        from scipy.spatial import cKDTree  # (on first use: a plan's start-up skips it)

        self._tree = cKDTree(self._points[: self._size].copy(),
                             boxsize=self._period if self._angles.size else None)
        self._indexed = self._size

    def _wrapped(self, x: np.ndarray) -> np.ndarray:
        """Weighted coordinates, angles shifted by whole turns into [0, period)."""
        y = x * self.weight - self._low
        a = self._angles
        if a.size:
            y[a] = np.mod(y[a], self._period[a])
            y[a] = np.where(y[a] >= self._period[a], 0.0, y[a])  # mod can round up to it
        return y

    def nearest(self, target: np.ndarray, k: int) -> np.ndarray:
        """Indices of the (at most) ``k`` nearest points, nearest first."""
        q = self._wrapped(np.asarray(target, dtype=np.float64))
        if self._tree is None or self._size <= _SCAN_ALL:  # every point, compiled
            tree_idx, lo = _NONE, 0
        else:
            _, i = self._tree.query(q, k=min(k, self._indexed))
            tree_idx, lo = np.atleast_1d(i).astype(np.int64), self._indexed
        # distances computed one way for every candidate, so equal points compare equal
        # wherever they are stored
        idx, d2 = _sqdists(self._points, tree_idx, lo, self._size, q, self._period)
        if k == 1:  # the same answer as the sort below: least distance, then least index
            return np.array([_least(idx, d2)])
        order = np.lexsort((idx, d2))[:k]
        return idx[order]
