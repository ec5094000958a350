"""`evaluate.step_check`: a solved plan's path re-integrated at half its step, the verdict
whether its step resolves it, as `pipeline.plan` records it and the command line reports it.
The references integrate the path again with the plain RK4 and hand-written dynamics of
tests/references.py and tests/conftest.py (no code shared with the package's integrators)."""

from __future__ import annotations

import numpy as np
import pytest
from tests import references as ref
from tests.conftest import pendulum_edge
from tests.swingup import GOAL, START, TOLERANCE, plan_swingup

from rrtcolearn import pipeline
from rrtcolearn.cli.planning import plan_summary, warn_unresolved
from rrtcolearn.config import paper_config
from rrtcolearn.evaluate import step_check
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.settings import PlannerSettings
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make


def _cartpole_swingup(dt: float, seed: int):
    """The shipped cart-pole swung up under |f| <= 219.9 N with random controls and the goal
    LQR (every edge a held input) at the step ``dt``."""
    system = make("cartpole")
    d = system.defaults
    problem = PlanningProblem.create(system, d["start"], d["goal"], 0.3, u_max=219.9,
                                     wrap_goal=True)
    plan = RRTCoLearn(problem, None, PlannerSettings(
        dt=dt, control_edges=True, max_duration=0.5, goal_lqr=True)).solve(
        TerminationCondition(None, 20000), seed)
    assert plan.solved
    return problem, plan


def _held_end(plan, x0, dt: float) -> np.ndarray:
    """The path's inputs held from ``x0``, edge after edge, by the reference RK4 at ``dt``."""
    x = np.asarray(x0, dtype=float)
    for e in plan.edges():
        x = ref.hold(ref.cartpole, x, e["control"], dt, round(e["duration"] / dt))[-1]
    return x


def _wrapped_offset(x: np.ndarray, goal: np.ndarray) -> np.ndarray:
    d = x - goal
    d[1] = (d[1] + np.pi) % (2 * np.pi) - np.pi  # the pole's angle, modulo a turn
    return d


def _wrapped_distance(x: np.ndarray, goal: np.ndarray) -> float:
    return float(np.linalg.norm(_wrapped_offset(x, goal)))


# dt 0.01, seed 1: the two ends 6e-5 apart; dt 0.02, seed 0: 0.10 apart, the half step's end
# 0.306 from the goal (tolerance 0.3: outside, but by less than the region: reported, not
# judged); dt 0.04, seed 4: 3.8 apart, the swing-up an artefact of the coarse step
@pytest.mark.parametrize("dt, seed, resolved", [(0.01, 1, True), (0.02, 0, True),
                                                 (0.04, 4, False)])
def test_the_half_step_verdict_matches_a_hand_integration(dt, seed, resolved):
    problem, plan = _cartpole_swingup(dt, seed)
    goal = np.asarray(problem.goal, dtype=float)
    full, half = _held_end(plan, problem.start, dt), _held_end(plan, problem.start, dt / 2)
    assert _wrapped_distance(full, goal) <= 0.3  # the plan's claim holds at its own step
    check = step_check(problem, plan)
    gap = np.linalg.norm(full - half)
    assert check["gap"] == pytest.approx(gap, rel=1e-6, abs=1e-9)
    assert check["goal_distance"] == pytest.approx(_wrapped_distance(half, goal), rel=1e-6)
    # the ends' offsets from the goal, the angle's wrapped: their difference
    offset = _wrapped_offset(full, goal) - _wrapped_offset(half, goal)
    assert check["goal_gap"] == pytest.approx(np.linalg.norm(offset), rel=1e-6, abs=1e-9)
    assert check["resolved"] is bool(np.linalg.norm(offset) < 0.3) is resolved
    assert check["valid"]  # no obstacles, no state bounds crossed


def test_the_command_line_warns_of_an_unresolved_plan(capsys):
    problem, plan = _cartpole_swingup(0.04, 4)
    plan.extra["step_check"] = step_check(problem, plan)
    row = plan_summary(plan)["half_step_check"]
    assert row.startswith("NOT resolved by the step dt = 0.04") and "3.88 from the goal" in row
    warn_unresolved(plan)
    assert "warning: NOT resolved" in " ".join(capsys.readouterr().err.split())
    problem, plan = _cartpole_swingup(0.02, 0)
    plan.extra["step_check"] = step_check(problem, plan)
    assert plan_summary(plan)["half_step_check"].startswith("resolved: at dt/2 the end moves")
    warn_unresolved(plan)
    assert capsys.readouterr().err == ""


def test_pipeline_plan_records_the_check_of_a_pendulum_swing_up(paper_model):
    p = plan_swingup(paper_model, 0, max_iterations=3000)
    assert p.solved
    w, dt = float(p.time_weight), float(p.dt)
    x = np.asarray(p.edges()[0]["from"], dtype=float)
    full = half = x
    for e in p.edges():
        full = pendulum_edge({**e, "from": full}, w, dt)[0][-1]
        half = pendulum_edge({**e, "from": half}, w, dt / 2)[0][-1]
    c = p.extra["step_check"]
    assert c["gap"] == pytest.approx(np.linalg.norm(full - half), rel=1e-6, abs=1e-12)
    d = half - GOAL
    d[0] = (d[0] + np.pi) % (2 * np.pi) - np.pi
    assert c["goal_distance"] == pytest.approx(np.linalg.norm(d), rel=1e-9)
    assert c["valid"] and c["resolved"] and c["gap"] < TOLERANCE
    assert "half_step_check" in plan_summary(p)


def test_a_plan_whose_edge_is_not_what_was_integrated_is_caught(capsys):
    """A path edge recorded with another held input than the one integrated (as a stale
    row of the tree once made an extremal look like a control edge): the replay at the
    plan's own step no longer ends on the path's last node, and the command line says so."""
    problem, plan = _cartpole_swingup(0.01, 1)
    assert step_check(problem, plan)["replays"]
    node = plan.path_nodes[len(plan.path_nodes) // 2]
    plan.tree.controls[node] = plan.tree.controls[node] + 1.0  # 1 N more than integrated
    plan.extra["step_check"] = check = step_check(problem, plan)
    assert not check["replays"]
    assert "does NOT re-simulate to its own path" in plan_summary(plan)["half_step_check"]
    warn_unresolved(plan)
    assert "warning:" in capsys.readouterr().err


def test_an_anytime_plan_replays_each_path_once(paper_model, monkeypatch):
    """Anytime planning asks `step_check` for its verdict on each new best path, and the
    plan's record is that verdict's check, not a second replay: no path is checked twice,
    and the record equals a fresh check of the plan kept."""
    from rrtcolearn import evaluate

    seen = []
    real = evaluate.step_check

    def counting(problem, plan):
        seen.append((id(plan.tree), tuple(plan.path_nodes)))
        return real(problem, plan)

    monkeypatch.setattr(evaluate, "step_check", counting)
    cfg = paper_config(plan={"anytime": True})
    p = pipeline.plan(paper_model, list(START), list(GOAL), TOLERANCE, seed=2, config=cfg,
                      time_limit=None, max_iterations=3000)
    assert p.solved and seen and len(seen) == len(set(seen))
    assert (id(p.tree), tuple(p.path_nodes)) in seen
    problem = pipeline.make_problem(paper_model.system, cfg, list(START), list(GOAL),
                                    TOLERANCE)
    assert p.extra["step_check"] == real(problem, p)


def test_a_path_whose_replays_part_on_the_way_is_not_resolved():
    """Judged at every node, not at the end alone: on x' = -a x + u at a step of a dt = 2.5
    (RK4 stable, but far off), one step of u = a from 0 then a long rest at u = 0 ends at
    about 0 at both steps, while the first node is 0.35 at the step and 0.91 at half of it.
    The references: RK4 on a linear ODE is x -> x_e + R(-a h) (x - x_e) with
    R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24, written here."""
    import sympy

    from rrtcolearn.planning.tree import Plan, PlannerData
    from rrtcolearn.systems.symbolic import build_system

    a, dt, rest = 50.0, 0.05, 40
    x, u = sympy.symbols("x u", real=True)
    system = build_system("stiff_decay", states=[x], inputs=[u], drift=[-a * x],
                          input_matrix=[[1]], input_weight=[[1]], state_low=[-2.0],
                          state_high=[2.0], angle_dims=[], description="x' = -50 x + u")

    def R(z):
        return 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24

    def held(x0, u0, h, steps):  # the hand RK4 of x' = -a x + u0
        xe = u0 / a
        return xe + R(-a * h) ** steps * (x0 - xe)

    x1 = held(0.0, a, dt, 1)
    x2 = held(x1, 0.0, dt, rest)
    tree = PlannerData(np.zeros(1), system.n_params, n_inputs=1)
    nan = np.full(1, np.nan)
    tree.add(np.array([x1]), 0, nan, np.full(system.n_params, np.nan), dt,
             (1.0 + 0.5 * a**2) * dt, np.array([[0.0], [x1]]), a, control=np.array([a]))
    tree.add(np.array([x2]), 1, nan, np.full(system.n_params, np.nan), rest * dt,
             rest * dt, np.array([[x1], [x2]]), 0.0, control=np.array([0.0]))
    problem = PlanningProblem.create(system, [0.0], [0.0], 0.1)
    plan = Plan("stiff_decay", np.zeros(1), np.zeros(1), 0.1, 1.0, dt, "exact", 0.0, 0.0, 1,
                tree, [0, 1, 2])
    check = step_check(problem, plan)
    assert check["replays"]
    half1 = held(0.0, a, dt / 2, 2)
    assert check["goal_gap"] == pytest.approx(abs(x2 - held(half1, 0.0, dt / 2, 2 * rest)),
                                              abs=1e-12) and check["goal_gap"] < 1e-6
    assert check["node_gap"] == pytest.approx(abs(half1 - x1), rel=1e-9)
    assert 0.5 < check["node_gap"]
    assert check["resolved"] is False  # the end alone would say resolved
    plan.extra["step_check"] = check
    assert "a node on the way 0.55" in plan_summary(plan)["half_step_check"]
