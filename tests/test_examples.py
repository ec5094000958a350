"""The README's bring-your-own-system example defines a system that passes check_system."""

import importlib.util
from pathlib import Path

from rrtcolearn.systems import list_systems, make


def test_damped_pendulum_example_registers_a_checked_system():
    path = Path(__file__).parents[1] / "examples" / "damped_pendulum.py"
    spec = importlib.util.spec_from_file_location("damped_pendulum_example", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # runs check_system and register
    assert "damped_pendulum" in list_systems()
    assert make("damped_pendulum").n_states == 2
