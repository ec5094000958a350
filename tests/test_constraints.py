"""Torque limits and obstacles: every returned path is re-simulated and checked independently."""

import numpy as np
import pytest
from tests.conftest import pendulum_edge, rk4_numpy
from tests.test_planner import check_plan_file

from rrtcolearn.config import load_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions, plan
from rrtcolearn.planning.problem import ProblemError

BLOCK = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}
# plans stop at their first solution or this many iterations: deterministic per seed, unlike a
# time limit, which a loaded machine reaches sooner
BUDGET = 20_000


def resimulated_states(d: dict) -> tuple[np.ndarray, np.ndarray]:
    """States and inputs (u = -lambda_omega, or a control edge's input) at every RK4 step of
    the plan's path."""
    xs, us = [], []
    for e in d["path"]:
        states, u, _ = pendulum_edge(e, d["time_weight"], d["dt"],
                                     d["u_max"] if d.get("limit_mode") == "saturate" else None)
        xs.append(states)
        us.append(u)
    return np.vstack(xs), np.concatenate(us)


def limited_model(pendulum, u_max: float, w: float) -> FittedModel:
    cfg = load_config(overrides=[f"system.u_max={u_max}", f"system.time_weight={w}"])
    data, _ = generate_data(pendulum, 2, 40000, u_max=u_max, time_weight=w)
    cleaned, _ = clean_data(data, seed=2)
    return FittedModel(pendulum, cfg, fit_functions(pendulum, cleaned, cfg),
                       float(cleaned.duration.max()), 1.5)


@pytest.fixture(scope="module", params=[(1.0, 0.1), (2.0, 1.0)], ids=["u1", "u2"])
def limited(request, pendulum):
    u_max, w = request.param
    return u_max, limited_model(pendulum, u_max, w)


def test_limited_dataset_never_exceeds_the_limit(pendulum):
    data, stats = generate_data(pendulum, 4, 2000, u_max=1.0, time_weight=0.1)
    assert stats.empty_simulations > 0
    rng = np.random.default_rng(0)
    for i in rng.choice(len(data), 20, replace=False):
        steps = round(data.duration[i] / 0.01)
        traj = rk4_numpy(np.r_[data.x0[i], data.costate[i], 0.0], 0.1, 0.01, steps)
        assert np.abs(traj[:, 3]).max() <= 1.0
        np.testing.assert_allclose(traj[-1, :2], data.x1[i], atol=1e-9)


def test_with_w_1_no_segment_leaves_rest_below_unit_torque(pendulum):
    """H* = 0 at omega = 0, sin(theta) = 0 forces |u| = sqrt(2w): why u_max = 1 needs w < 1/2."""
    x = np.array([[-np.pi, 0.0]] * 64)
    p = np.linspace(-np.pi / 2 + 1e-3, 3 * np.pi / 2 - 1e-3, 64)[:, None]
    lam, ok = pendulum.costate_from_params(x, p, 1.0)
    np.testing.assert_allclose(np.abs(lam[ok, 1]), np.sqrt(2.0), atol=1e-9)


def test_torque_limited_swing_up(limited):
    u_max, model = limited
    for seed in range(3):
        p = plan(model, [-np.pi, 0], [0, 0], 0.1, seed=seed, time_limit=None,
                 max_iterations=BUDGET)
        assert p.solved
        d = p.to_dict()
        assert d["u_max"] == u_max
        check_plan_file(d)
        _, u = resimulated_states(d)
        assert np.abs(u).max() <= u_max + 1e-9
        assert d["max_abs_u"] == pytest.approx(np.abs(u).max(), abs=1e-9)


def test_obstacle_path_stays_free(paper_model):
    for seed in range(3):
        p = plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=seed, obstacles=[BLOCK],
                 time_limit=None, max_iterations=BUDGET)
        assert p.solved
        d = p.to_dict()
        check_plan_file(d)
        x, _ = resimulated_states(d)
        wrapped = x.copy()
        wrapped[:, 0] -= 2 * np.pi * np.floor((x[:, 0] + 1.5 * np.pi) / (2 * np.pi))
        inside = np.all((wrapped >= BLOCK["low"]) & (wrapped <= BLOCK["high"]), axis=1)
        assert not inside.any()
        assert d["obstacles"] == [BLOCK]


def test_user_validity_callable(paper_model):
    def is_valid(states):
        return states[:, 1] < 2.0  # never faster than 2 rad/s

    p = plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=0, is_valid=is_valid,
             time_limit=None, max_iterations=BUDGET)
    assert p.solved
    x, _ = resimulated_states(p.to_dict())
    assert x[:, 1].max() < 2.0


@pytest.mark.parametrize("start, goal, where", [
    ([-1.5, 1.0], [0, 0], "start"),
    ([-np.pi, 0], [-1.6, 2.0], "goal"),
])
def test_start_or_goal_inside_an_obstacle_is_refused(paper_model, start, goal, where):
    with pytest.raises(ProblemError, match=f"the {where} .* inside an obstacle"):
        plan(paper_model, start, goal, 0.1, obstacles=[BLOCK])


@pytest.mark.parametrize("spec, message", [
    ({"type": "box", "low": [0, 0, 0], "high": [1, 1, 1]}, "2 low"),
    ({"type": "box", "low": [1, 0], "high": [0, 1]}, "exceed"),
    ({"type": "halfplane", "normal": [0, 0], "offset": 1}, "non-zero"),
    ({"type": "circle"}, "unknown obstacle type"),
    ("box:-1,-1,1,1", r"a dict such as .* not 'box:-1,-1,1,1' \(str\)"),  # the CLI's form
    (3, r"not 3 \(int\)"),
])
def test_malformed_obstacles_are_refused(paper_model, spec, message):
    with pytest.raises(ProblemError, match=message):
        plan(paper_model, [-np.pi, 0], [0, 0], 0.1, obstacles=[spec])


def test_an_obstacle_covers_its_region_on_every_turn():
    """A box given on any turn of an angle, or across the end of the turn the states are
    wrapped into, forbids the same states on every turn."""
    from rrtcolearn.planning.problem import PlanningProblem, ProblemError
    from rrtcolearn.systems import make

    pendulum = make("pendulum")  # theta wrapped into [-3 pi / 2, pi / 2)
    two_pi = 2 * np.pi
    across = [{"type": "box", "low": [1.2, -0.5], "high": [2.0, 0.5]}]
    p = PlanningProblem.create(pendulum, [-3.0, 0.0], [0.0, 0.0], 0.1, obstacles=across)
    x = np.array([[1.3, 0.0], [1.8, 0.0], [1.8 - two_pi, 0.0], [1.3 - two_pi, 0.0],
                  [1.3 + two_pi, 0.0], [1.0, 0.0], [2.1 - two_pi, 0.0]])
    assert p.validity(x).tolist() == [False] * 5 + [True, True]
    elsewhere = [{"type": "box", "low": [3.0, -0.5], "high": [3.3, 0.5]}]  # (pi, 0) on it
    with pytest.raises(ProblemError, match=r"the start .* lies inside an obstacle"):
        PlanningProblem.create(pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, obstacles=elsewhere)
    ring = [{"type": "box", "low": [-10.0, 1.0], "high": [10.0, 1.5]}]  # every theta
    p = PlanningProblem.create(pendulum, [-3.0, 0.0], [0.0, 0.0], 0.1, obstacles=ring)
    theta = np.linspace(-20, 20, 101)
    assert not p.validity(np.c_[theta, np.full(101, 1.2)]).any()
    assert p.validity(np.c_[theta, np.full(101, 0.9)]).all()
