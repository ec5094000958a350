"""Goal simulations: data integrated backwards in time from the query's goal.

Each point (x0, goal) must be an ordinary data point: its stored parameters give back its
costate on H* = 0 at x0, and integrating forward from x0 with that costate for the stored
duration ends at the goal with the stored cost.
"""

import numpy as np
import pytest

from rrtcolearn.data.generate import generate_data
from rrtcolearn.integrate import rollout
from rrtcolearn.systems import make

CASES = {
    "pendulum": np.array([np.pi, 0.0]),
    "double_integrator": np.array([0.5, -0.3]),
    "cartpole": np.array([0.0, np.pi, 0.0, 0.0]),
}


def _goal_data(system, goal, seed=5, goal_simulations=60, chunk_size=2000):
    return generate_data(system, seed, 20, goal_simulations=goal_simulations, goal=goal,
                         chunk_size=chunk_size, max_cost=2.0, max_state_distance=1.5)


@pytest.mark.parametrize("name", sorted(CASES))
def test_goal_points_end_at_the_goal_and_resimulate(name):
    system, goal = make(name), CASES[name]
    data, _ = _goal_data(system, goal)
    back = data.simulation >= 20  # ids of goal simulations follow the forward ones
    assert back.sum() > 100
    d = {k: v[back] for k, v in data.arrays().items()}
    # the goal, shifted by whole turns only where x0's angles were wrapped into the box
    shift = d["x1"] - goal
    turns = shift[:, list(system.angle_dims)] / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)
    others = [i for i in range(system.n_states) if i not in system.angle_dims]
    assert np.array_equal(shift[:, others], np.zeros_like(shift[:, others]))
    # parameters determine the costate, and the costate lies on H* = 0
    lam, valid = system.costate_from_params(d["x0"], d["params"], 1.0)
    assert valid.all()
    np.testing.assert_allclose(lam, d["costate"], rtol=1e-9, atol=1e-9)
    u = system.optimal_control(d["x0"], d["costate"])
    assert np.abs(system.hamiltonian(d["x0"], d["costate"], u, 1.0)).max() < 1e-8
    assert np.all(d["cost"] > 0) and np.all(d["cost"] <= 2.0 + 1e-12)
    # forward from x0 with that costate for the duration: ends at x1 with the stored cost
    rng = np.random.default_rng(0)
    for i in rng.choice(len(d["x0"]), 20, replace=False):
        steps = round(d["duration"][i] / 0.01)
        z = rollout(system, np.r_[d["x0"][i], lam[i], 0.0], 1.0, 0.01, steps)[-1]
        np.testing.assert_allclose(z[: system.n_states], d["x1"][i], atol=1e-6)
        assert abs(z[-1] - d["cost"][i]) < 1e-6


def test_goal_data_independent_of_chunk_size_and_of_forward_data():
    system, goal = make("double_integrator"), CASES["double_integrator"]
    a, _ = _goal_data(system, goal, chunk_size=2000)
    b, _ = _goal_data(system, goal, chunk_size=7)
    for k, v in a.arrays().items():
        assert np.array_equal(v, b.arrays()[k]), k
    none, _ = _goal_data(system, goal, goal_simulations=0)
    forward = a.simulation < 20
    for k, v in none.arrays().items():  # adding goal simulations leaves the others alone
        assert np.array_equal(v, a.arrays()[k][forward]), k


def test_goal_simulations_need_a_goal():
    with pytest.raises(ValueError, match="goal"):
        generate_data(make("double_integrator"), 1, 10, goal_simulations=5)
