"""The planner's nearest-neighbour index over tree nodes against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from rrtcolearn.planning.nearest import NodeIndex


@pytest.mark.parametrize("angles", [False, True])
def test_index_matches_brute_force(angles):
    rng = np.random.default_rng(0)
    weight = np.array([1.0, 0.5, 2.0])
    low = np.array([-np.pi, np.nan, np.nan]) if angles else None
    index = NodeIndex(weight, low, rebuild_every=50)
    points = rng.uniform(-8.0, 8.0, (1000, 3))
    points[500] = points[499]  # a tie, split across the k-d tree and the buffer later on
    for i, p in enumerate(points):
        index.add(p)
        assert len(index) == i + 1
        if i % 37 == 0 or i == 999:
            q = rng.uniform(-8.0, 8.0, 3) if i != 999 else points[499]
            diff = (points[: i + 1] - q) * weight
            if angles:  # angle coordinate 0 compared modulo a turn
                diff[:, 0] = np.mod(diff[:, 0] + np.pi, 2 * np.pi) - np.pi
            d2 = np.einsum("ij,ij->i", diff, diff)
            for k in (1, 7, 60):
                expected = np.lexsort((np.arange(i + 1), d2))[:k]
                np.testing.assert_array_equal(index.nearest(q, k), expected)


def test_index_wraps_angles_by_whole_turns():
    index = NodeIndex(np.ones(2), np.array([-np.pi, np.nan]), rebuild_every=2)
    for p in ([3.0, 0.0], [-3.0, 0.0], [0.0, 0.0], [3.0 + 4 * np.pi, 0.1]):
        index.add(np.array(p))
    # -3.1 is 0.18 from 3.0 (and from 3 + 4 pi) across the seam, 0.1 from -3.0
    np.testing.assert_array_equal(index.nearest(np.array([-3.1, 0.0]), 3), [1, 0, 3])
