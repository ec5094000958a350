"""The planner contract over every registered planner on two systems (`check_planner`): an
easy problem with an input bound, a state constraint and an obstacle is solved, the plan
re-simulates, keeps the limits, the box and the obstacle, and the same seed gives the same
plan. A planner that cannot take a problem says why (`Planner.supports`)."""

from __future__ import annotations

import numpy as np
import pytest

from rrtcolearn import pipeline, planners
from rrtcolearn.config import load_config
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

# system -> (start, goal, tolerance, u_max, state_high, obstacle)
EASY = {
    "pendulum": ([-3.0, 0.0], [-2.2, 0.8], 0.2, 2.0, [None, 2.5],
                 {"type": "box", "low": [-2.9, 1.6], "high": [-2.5, 2.4]}),
    "double_integrator": ([-1.0, 0.0], [0.5, 0.0], 0.2, 2.0, [None, 1.5],
                          {"type": "box", "low": [-0.4, -2.0], "high": [0.4, -0.6]}),
}

# An iteration budget decides every planner that counts iterations (the same plan on any
# machine); the time limit is only a backstop for OMPL's, which stop at their first solution.
BUDGET = {"max_iterations": 20_000, "time_limit": 300.0}


@pytest.fixture(scope="module")
def models(paper_model, tmp_path_factory):
    cfg = load_config(overrides=['system.name="double_integrator"',
                                 "generate.n_simulations=6000", "clean.k_max=500"])
    run = tmp_path_factory.mktemp("di")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return {"pendulum": paper_model, "double_integrator": pipeline.fit(cfg, run)}


@pytest.fixture(scope="module")
def direct_model():
    from rrtcolearn.baselines.direct import fit_direct_model, generate_direct_dataset

    return fit_direct_model(generate_direct_dataset(300, seed=3)[0], intermediate=True)


def easy_problem(system_name: str) -> PlanningProblem:
    start, goal, tol, u_max, high, box = EASY[system_name]
    return PlanningProblem.create(make(system_name), start, goal, tol, u_max=u_max,
                                  state_high=high, obstacles=[box])


def build(name: str, system_name: str, request) -> planners.Planner:
    if name == "rrtcolearn":
        return planners.make(name, model=request.getfixturevalue("models")[system_name])
    if name == "direct":
        if system_name != "pendulum":
            return planners.make(name)  # no model needed to say it cannot
        return planners.make(name, model=request.getfixturevalue("direct_model"))
    return planners.make(name)


def test_registry():
    assert planners.list_planners()[:2] == ["rrtcolearn", "random-rrt"]
    assert {"ompl-RRT", "ompl-KPIECE1", "ompl-EST", "direct"} <= set(planners.list_planners())
    with pytest.raises(ValueError, match="unknown planner 'SST'; known planners: rrtcolearn"):
        planners.make("SST")
    assert isinstance(planners.make("random-rrt"), planners.Planner)


@pytest.mark.parametrize("system_name", list(EASY))
@pytest.mark.parametrize("name", planners.list_planners())
def test_planner_contract(name, system_name, request):
    planner = build(name, system_name, request)
    problem = easy_problem(system_name)
    reason = planner.supports(problem)
    if name == "direct" and system_name != "pendulum":
        assert reason is not None and "pendulum" in reason
        with pytest.raises(ValueError, match="pendulum"):
            planners.make("direct", model=object()).solve(problem, TerminationCondition(1.0))
        return
    plan = planners.check_planner(planner, problem, seed=1, **BUDGET)
    assert plan.extra["planner"] == name
    # the obstacle and the state constraint are respected along every stored edge
    states = np.concatenate([plan.tree.trajectories[i] for i in plan.path_nodes])
    assert problem.validity(states).all() and problem.within_bounds(states).all()


def test_a_random_control_peer_needs_an_input_bound(pendulum):
    problem = PlanningProblem.create(pendulum, [-3.0, 0.0], [-2.2, 0.8], 0.2)
    planner = planners.make("random-rrt")
    assert "input bound" in planner.supports(problem)
    with pytest.raises(ValueError, match="input bound"):
        planner.solve(problem, TerminationCondition(1.0))
    bounded = planners.make("random-rrt", u_max=2.0)
    assert bounded.supports(problem) is None
    plan = planners.check_planner(bounded, problem, **BUDGET)
    assert plan.max_abs_u <= 2.0


def test_a_broken_planner_fails_the_check(pendulum):
    """check_planner catches a planner whose stored path is not what it executes."""
    inner = planners.make("random-rrt")

    class Lying:
        name = "lying"

        def supports(self, problem):
            return inner.supports(problem)

        def solve(self, problem, termination, seed=0):
            plan = inner.solve(problem, termination, seed)
            plan.tree.costs[plan.path_nodes[-1]] *= 0.5  # claims a cheaper last edge
            return plan

    with pytest.raises(planners.PlannerCheckError, match="path cost"):
        planners.check_planner(Lying(), easy_problem("pendulum"))


def test_propagate_is_one_rk4_with_or_without_compiled_kernels(pendulum):
    """A System built by hand without ``propagate_jit`` propagates with the numpy RK4 step
    (`integrate.rk4_step`): the same states as the compiled kernel, and the same box stop."""
    import dataclasses

    from rrtcolearn.integrate import propagate, propagate_controls

    plain = dataclasses.replace(pendulum, propagate_jit=None)
    x0, u = np.array([-3.0, 0.2]), np.array([1.3])
    np.testing.assert_allclose(propagate(plain, x0, u, 0.01, 150),
                               propagate(pendulum, x0, u, 0.01, 150), rtol=0, atol=1e-12)
    high = np.array([np.inf, 1.0])
    a = propagate(plain, x0, u, 0.01, 500, high=high)
    b = propagate(pendulum, x0, u, 0.01, 500, high=high)
    assert len(a) == len(b) < 501 and a[-1, 1] > 1.0
    steps = np.array([30, 20])
    path = propagate_controls(pendulum, x0, [[1.3], [-0.5]], steps, 0.01)
    assert path.shape == (51, 2)
    np.testing.assert_array_equal(path[:31], propagate(pendulum, x0, u, 0.01, 30))


def test_propagate_draws_is_propagate_draw_by_draw(pendulum):
    """A batch of control draws (`propagate_draws`, one compiled call) gives each draw's
    `propagate` states, its count and how it stopped, compiled or in numpy."""
    import dataclasses

    from rrtcolearn.integrate import propagate, propagate_draws

    x0 = np.array([-3.0, 0.2])
    inputs, lengths = np.array([[1.3], [-2.0], [0.4]]), np.array([40, 300, 7])
    low, high = np.array([-np.inf, -1.5]), np.array([np.inf, 1.5])
    for system in (pendulum, dataclasses.replace(pendulum, propagate_jit=None)):
        states, counts, stops = propagate_draws(system, x0, inputs, lengths, 0.01, low, high)
        begin = 0
        for u, k, count, stop in zip(inputs, lengths, counts, stops, strict=True):
            one = propagate(pendulum, x0, u, 0.01, int(k), low, high)[1:]
            np.testing.assert_allclose(states[begin : begin + count], one, rtol=0, atol=1e-12)
            outside = not (np.all(low <= one[-1]) and np.all(one[-1] <= high))
            assert count == len(one) and stop == int(outside)
            begin += count
        assert begin == len(states) and stops.tolist() == [0, 1, 0]


def test_propagate_controls_chains_each_control_from_the_last_state(pendulum):
    """`propagate_controls` (one compiled call with the controls chained, or control by
    control in numpy): each control held from where the one before ended, as `propagate`
    integrates it, and a state outside the box ends the whole path there (kept as its last
    row)."""
    import dataclasses

    from rrtcolearn.integrate import propagate, propagate_controls

    x0 = np.array([-3.0, 0.2])
    controls, steps = np.array([[1.3], [-0.5], [0.0], [3.0]]), np.array([30, 0, 20, 400])
    high = np.array([np.inf, 1.0])
    want, x = [x0[None]], x0
    for u, k in zip(controls, steps, strict=True):  # the reference: control by control
        traj = propagate(pendulum, x, u, 0.01, int(k), high=high)
        want.append(traj[1:])
        x = traj[-1]
        if len(traj) < k + 1:
            break
    want = np.concatenate(want)
    assert want[-1, 1] > 1.0 and len(want) < 1 + steps.sum()  # the box stopped it
    for system in (pendulum, dataclasses.replace(pendulum, propagate_jit=None)):
        got = propagate_controls(system, x0, controls, steps, 0.01, high=high)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        free = propagate_controls(system, x0, controls[:3], steps[:3], 0.01)
        assert free.shape == (51, 2)
        np.testing.assert_allclose(free[31:], propagate(pendulum, free[30], controls[2], 0.01,
                                                         20)[1:], rtol=0, atol=1e-12)


def test_a_peer_edge_that_turns_invalid_ends_at_its_last_valid_state(pendulum):
    """A peer's path executed here: an edge that leaves the state constraints or enters an
    obstacle is kept up to its last valid state, with the duration and cost of those steps,
    so the plan re-simulates to what it records (`evaluate.check_plan`)."""
    import json

    from rrtcolearn.baselines.base import control_plan
    from rrtcolearn.evaluate import check_plan

    walls = [{"type": "halfplane", "normal": [0.0, 1.0], "offset": 2.0},  # |omega| >= 2
             {"type": "halfplane", "normal": [0.0, -1.0], "offset": 2.0}]
    for kwargs in ({"state_low": [None, -1.0], "state_high": [None, 1.0]},
                   {"obstacles": walls}):
        problem = PlanningProblem.create(pendulum, [-np.pi, 0.0], [0.0, 0.0], 0.1, u_max=5.0,
                                         **kwargs)
        p = control_plan(problem, np.array([[5.0], [-5.0]]), np.array([400, 10]), dt=0.01,
                         time_weight=1.0, cpu_s=0.0, wall_s=0.0, iterations=1,
                         graph_states=3, extra={})
        assert p.status == "approximate" and p.tree.n_nodes == 2 and not p.extra["valid"]
        edge = p.edges()[0]
        assert 0 < edge["duration"] < 4.0
        d = json.loads(json.dumps(p.to_dict()))
        assert check_plan(pendulum, d)["max_gap"] == 0.0
