"""k-nearest-neighbour index: one small interface over scipy's KD-tree."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class NeighbourIndex:
    """Euclidean k-NN over fixed points (the paper's distance on (x0, x1))."""

    def __init__(self, points: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self._tree = cKDTree(self.points, balanced_tree=False, compact_nodes=False)

    def __len__(self) -> int:
        return self.points.shape[0]

    def query(self, x: np.ndarray, k: int, max_distance: float = np.inf
              ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices (Q, k) of the k nearest points to each row of ``x`` (Q, D).

        Neighbours farther than ``max_distance`` are reported with distance inf and index
        ``len(self)``; bounding the search makes queries far from the data cheap.
        """
        dist, idx = self._tree.query(np.atleast_2d(x), k=k, distance_upper_bound=max_distance)
        if k == 1:
            dist, idx = dist[:, None], idx[:, None]
        return dist, idx
