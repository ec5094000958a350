"""V's coverage grid is dilated without scipy.ndimage: the same cells as its maximum_filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import maximum_filter

from rrtcolearn.learn.models import _dilate


@pytest.mark.parametrize("shape", [(7,), (5, 1), (6, 4), (3, 4, 5), (4, 3, 5, 6), (2, 2, 2, 2, 3)])
@pytest.mark.parametrize("density", [0.0, 0.05, 0.5, 1.0])
def test_dilation_is_scipys_maximum_filter(shape, density):
    grid = np.random.default_rng(len(shape)).random(shape) < density
    expected = maximum_filter(grid, size=3, mode="constant", cval=False)
    got = _dilate(grid)
    assert got.dtype == bool and np.array_equal(got, expected)
    assert not np.shares_memory(got, grid)
