"""The public contract every registered system must pass (like scikit-learn's check_estimator)."""

import pytest

from rrtcolearn.systems import list_systems, make
from rrtcolearn.systems.check import check_system


@pytest.mark.parametrize("name", list_systems())
def test_registered_system_passes_check_system(name):
    check_system(make(name), n_samples=100)
