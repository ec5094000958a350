"""The LQR goal connection (plan.goal_lqr, planning/lqr.py) on the planar quadrotor, planned
without learned functions (random-control edges and the connection only): its edges
re-simulate exactly within the input and state boxes, obstacles are avoided, the same seed
grows the same tree, a goal that is no equilibrium switches it off."""

import math

import numpy as np
import pytest
from tests import references as ref

from rrtcolearn.config import PAPER, PlanConfig
from rrtcolearn.evaluate import resimulate
from rrtcolearn.integrate import propagate
from rrtcolearn.planning.lqr import GoalLQR, build_goal_lqr, step_jacobians
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make
from rrtcolearn.systems.quadrotor import F_MAX, HOVER_THRUST, make_quadrotor

WALL = {"type": "box", "low": [-0.15, -1.0, -10.0, -10.0, -10.0, -20.0],
        "high": [0.15, 0.1, 10.0, 10.0, 10.0, 20.0]}


@pytest.fixture(scope="module")
def quad():
    return make_quadrotor()


def _problem(quad, goal=None, **kw):
    d = quad.defaults
    return PlanningProblem.create(quad, d["start"], d["goal"] if goal is None else goal, 0.1,
                                  **kw)


def _plan(problem, seed, iterations=3000, **settings):
    planner = RRTCoLearn(problem, None, PlannerSettings(control_edges=True, max_duration=0.5,
                                                        **settings))
    return planner.solve(TerminationCondition(None, iterations), seed)


def test_the_setting_defaults_to_auto_and_the_paper_has_none():
    assert PlanConfig().goal_lqr is None and PlannerSettings().goal_lqr is None
    assert PAPER["plan"]["goal_lqr"] is False


def test_hover_equilibrium_gain_and_a_stable_loop(quad):
    lqr = build_goal_lqr(_problem(quad), 0.01)
    assert isinstance(lqr, GoalLQR)
    np.testing.assert_allclose(lqr.x_e, quad.defaults["goal"], atol=1e-9)
    np.testing.assert_allclose(lqr.u_e, [HOVER_THRUST, HOVER_THRUST], rtol=1e-9)
    assert lqr.spectral_radius < 1.0
    np.testing.assert_allclose(lqr.u_low, [0.0, 0.0])
    np.testing.assert_allclose(lqr.u_high, [F_MAX, F_MAX])


def test_without_input_limits_the_input_is_free_or_the_truncation_box(pendulum):
    free = build_goal_lqr(PlanningProblem.create(pendulum, [-np.pi, 0], [0, 0], 0.1), 0.01)
    assert isinstance(free, GoalLQR) and np.all(np.isinf(free.u_high))
    cut = build_goal_lqr(PlanningProblem.create(pendulum, [-np.pi, 0], [0, 0], 0.1,
                                                u_max=2.0), 0.01)
    np.testing.assert_allclose([cut.u_low[0], cut.u_high[0]], [-2.0, 2.0])


def _check_path(quad, plan, problem):
    """Every edge of the path re-simulates exactly; inputs in the box, states in the box and
    outside the obstacles."""
    assert plan.solved and plan.extra["connection"] == "lqr"
    r = resimulate(quad, plan)
    assert r["max_gap"] < 1e-9 and r["max_cost_gap"] < 1e-9
    low, high = quad.input_limits()
    tree = plan.tree
    lqr_links = 0
    for node in plan.path_nodes[1:]:
        u, traj = tree.controls[node], tree.trajectories[node]
        assert np.all(np.isfinite(u)), "the path holds control edges only"
        assert np.all(low <= u) and np.all(u <= high)
        # the stored states are the RK4 of the held input from the parent
        np.testing.assert_allclose(traj, propagate(quad, traj[0], u, plan.dt, len(traj) - 1),
                                   rtol=0, atol=1e-12)
        assert problem.within_bounds(traj).all()
        if problem.validity:
            assert problem.validity(traj).all()
        lqr_links += 1
    assert lqr_links > 1
    assert problem.goal_distance(tree.states[plan.path_nodes[-1]])[0] <= 0.1


def test_standard_query_solved_with_default_settings(quad):
    """goal_lqr auto: switched on once the tree stalls near the goal, then it connects."""
    problem = _problem(quad)
    for seed in range(2):
        p = _plan(problem, seed)
        assert "lqr" in p.extra["connections_switched_on"]
        _check_path(quad, p, problem)


def test_lqr_edges_resimulate_within_the_boxes(quad):
    problem = _problem(quad)
    p = _plan(problem, 0, goal_lqr=True)
    assert p.iterations < 50 and "connections_switched_on" not in p.extra
    _check_path(quad, p, problem)


def test_obstacles_are_avoided(quad):
    problem = _problem(quad, obstacles=[WALL])
    free = _plan(_problem(quad), 1, goal_lqr=True)
    # the connection's path without the wall runs through it
    states = np.concatenate([free.tree.trajectories[i] for i in free.path_nodes[1:]])
    assert not problem.validity(states).all()
    p = _plan(problem, 1, goal_lqr=True)
    _check_path(quad, p, problem)
    assert p.extra["goal_lqr"]["tries"] > 1


def test_same_seed_same_tree(quad):
    problem = _problem(quad, obstacles=[WALL])
    a, b = (_plan(problem, 1, goal_lqr=True).to_dict() for _ in range(2))
    assert a["tree"] == b["tree"] and a["path"] == b["path"]


def test_a_goal_that_is_no_equilibrium_switches_it_off(quad):
    moving = [1.0, 0.0, 0.0, 1.0, 0.0, 0.0]  # at 1 m/s: no input holds it
    reason = build_goal_lqr(_problem(quad, moving), 0.01)
    assert isinstance(reason, str) and "no equilibrium" in reason
    p = _plan(_problem(quad, moving), 0, iterations=100, goal_lqr=True)
    assert not p.solved and p.iterations == 100
    assert "no equilibrium" in p.extra["goal_lqr"]["off"]
    assert "LQR goal connection off" in p.extra["diagnosis"]
    # auto: switched on (and found off) once the tree stalls; the planner runs on
    auto = _plan(_problem(quad, moving), 0, iterations=600)
    assert auto.iterations == 600 and "off" in auto.extra["goal_lqr"]


def test_off_grows_the_tree_without_it(quad):
    p = _plan(_problem(quad), 0, iterations=300, goal_lqr=False)
    assert "goal_lqr" not in p.extra and p.extra.get("connection") is None


def test_a_system_without_an_input_box_needs_learned_functions():
    from rrtcolearn.errors import ConfigError

    system = make("double_integrator")
    problem = PlanningProblem.create(system, [-1.0, 0.0], [1.0, 0.0], 0.1)
    with pytest.raises(ConfigError, match="random-control"):
        RRTCoLearn(problem, None, PlannerSettings(goal_lqr=True))


def test_the_compiled_loop_is_the_numpy_loop(quad):
    """`integrate.closed_loop_jit` and the numpy loop of a hand-built System stop at the same
    step for the same reason with the same states and saturated inputs."""
    import dataclasses

    problem = _problem(quad)
    lqr = build_goal_lqr(problem, 0.01)
    plain = dataclasses.replace(problem, system=dataclasses.replace(quad, closed_loop_jit=None))
    lqr_plain = dataclasses.replace(lqr, problem=plain)
    low, high = problem.constraint_box
    rng = np.random.default_rng(3)
    ends = set()
    for _ in range(12):
        x0 = rng.uniform(problem.state_low, problem.state_high)
        a = lqr.run(x0, 300, (low, high), lambda s: problem.goal_distance(s) <= 0.1)
        b = lqr_plain.run(x0, 300, (low, high), lambda s: problem.goal_distance(s) <= 0.1)
        assert a.end == b.end
        np.testing.assert_allclose(a.states, b.states, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.inputs, b.inputs, rtol=0, atol=1e-9)
        assert np.all(a.inputs >= lqr.u_low) and np.all(a.inputs <= lqr.u_high)
        ends.add(a.end)
    assert len(ends) >= 2  # more than one way of stopping was compared


# --- against independent references (issue 34): the reference dynamics of
# tests/references.py, a plain RK4 written there, scipy's Riccati solver on the test's own
# (A, B, Q, R) and the gain's formula by hand. The spectral radius alone (above) passes a
# gain scaled by 0.7 or the wrong Riccati solution.

REFERENCES = {"quadrotor": ref.quadrotor, "cartpole": ref.cartpole, "pendulum": ref.pendulum}
DT = 0.02


def _reference_lqr(name: str):
    """(problem, x_e, u_e, A, B, Q, R) for the system's default goal: the equilibrium from
    the sources (upright at rest; the quadrotor hovers at m g / 2 a rotor), the RK4 step map
    of the reference dynamics linearised exactly (RK4 of the linearisation: at an
    equilibrium every stage sits at x_e), and Bryson's weights from the problem's boxes as
    `build_goal_lqr` documents them."""
    system = make(name)
    d = system.defaults
    problem = PlanningProblem.create(system, d["start"], d["goal"], 0.1)
    x_e = np.asarray(d["goal"], dtype=float)
    u_e = np.full(system.n_inputs, ref.QUADROTOR["m"] * ref.QUADROTOR["g"] / 2) \
        if name == "quadrotor" else np.zeros(system.n_inputs)
    f = REFERENCES[name]
    Ac = ref.complex_step_jacobian(lambda x: f(x[None], u_e[None].astype(complex))[0], x_e)
    Bc = ref.complex_step_jacobian(lambda u: f(x_e[None].astype(complex), u[None])[0], u_e)
    A, B, term = np.zeros_like(Ac), np.zeros_like(Bc), np.eye(len(x_e))
    for k in range(5):  # sum_k (dt Ac)^k / k!, dt sum_k (dt Ac)^k / (k + 1)! Bc
        A += term / math.factorial(k)
        if k < 4:
            B += DT * term @ Bc / math.factorial(k + 1)
        term = term @ (DT * Ac)
    half_x = 0.5 * (problem.state_high - problem.state_low)
    half_x[list(system.angle_dims)] = np.pi
    low_u, high_u = system.input_limits()
    half_u = 0.5 * (high_u - low_u)
    r = np.where(np.isfinite(half_u), 1.0 / half_u**2, 1.0)  # R = identity where free
    return problem, x_e, u_e, A, B, np.diag(DT / half_x**2), np.diag(DT * r)


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_the_discretisation_is_a_plain_rk4_step(name):
    """The linearisation of RK4's step in closed form agrees with central differences of a
    plain RK4 step of the reference (so the closed form is what the connection means), and
    `step_jacobians` (the package's) with both."""
    problem, x_e, u_e, A, B, _, _ = _reference_lqr(name)
    f, n = REFERENCES[name], len(x_e)
    z, h = np.concatenate([x_e, u_e]), 1e-5
    cols = []
    for j in range(z.size):
        e = np.zeros(z.size)
        e[j] = h
        plus, minus = z + e, z - e
        cols.append((ref.hold(f, plus[:n], plus[n:], DT, 1)[-1]
                     - ref.hold(f, minus[:n], minus[n:], DT, 1)[-1]) / (2 * h))
    jac = np.stack(cols, axis=1)
    np.testing.assert_allclose(jac[:, :n], A, atol=1e-7)
    np.testing.assert_allclose(jac[:, n:], B, atol=1e-7)
    A_pkg, B_pkg = step_jacobians(problem.system, x_e, u_e, DT)
    np.testing.assert_allclose(A_pkg, A, atol=1e-7)
    np.testing.assert_allclose(B_pkg, B, atol=1e-7)


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_the_gain_is_scipys_riccati_solution(name):
    """K = (R + B'PB)^-1 B'PA with P from `scipy.linalg.solve_discrete_are` on the test's
    own (A, B, Q, R); the equilibrium where the sources put it."""
    from scipy.linalg import solve_discrete_are

    problem, x_e, u_e, A, B, Q, R = _reference_lqr(name)
    P = solve_discrete_are(A, B, Q, R)
    K = np.linalg.inv(R + B.T @ P @ B) @ B.T @ P @ A
    lqr = build_goal_lqr(problem, DT)
    assert isinstance(lqr, GoalLQR), lqr
    np.testing.assert_allclose(lqr.x_e, x_e, atol=1e-9)
    np.testing.assert_allclose(lqr.u_e, u_e, atol=1e-9)
    assert lqr.K.shape == K.shape == (problem.system.n_inputs, problem.system.n_states)
    np.testing.assert_allclose(lqr.K, K, rtol=1e-6, atol=1e-8 * np.abs(K).max())
    np.testing.assert_allclose(lqr.P, P, rtol=1e-6, atol=1e-8 * np.abs(P).max())
    mu = np.abs(np.linalg.eigvals(A - B @ K))
    rho = mu.max()
    assert lqr.spectral_radius == pytest.approx(rho, rel=1e-6) and rho < 1.0
    # the loop's horizon: 5 time constants of its slowest mode, here every mode moved
    # (none within 1e-6 of the unit circle)
    assert rho < 1.0 - 1e-6
    tau = -DT / math.log(rho)
    assert lqr.time_constant == pytest.approx(tau, rel=1e-5)
    assert lqr.horizon == pytest.approx(5.0 * tau, rel=1e-5)


def test_a_mode_the_loop_does_not_move_sets_no_horizon():
    """dynobench's unicycle at kink_0's goal: its sideways offset is not controllable at the
    linearisation (closed-loop eigenvalue 1 to 1e-11); the horizon comes from the slowest
    mode the loop does move, here computed from the package's own step Jacobians and gain."""
    from rrtcolearn.dynobench import make_system, planning_problem, read_problem

    kink = read_problem("unicycle1_v0/kink_0")
    system = make_system(kink)
    problem = planning_problem(kink, system, 0.1)
    lqr = build_goal_lqr(problem, DT)
    assert isinstance(lqr, GoalLQR), lqr
    A, B = step_jacobians(system, lqr.x_e, lqr.u_e, DT)
    mu = np.sort(np.abs(np.linalg.eigvals(A - B @ lqr.K)))
    assert mu[-1] > 1.0 - 1e-9  # the unmoved mode
    moved = mu[mu < 1.0 - 1e-6]
    assert len(moved) == len(mu) - 1
    assert lqr.time_constant == pytest.approx(-DT / math.log(moved.max()), rel=1e-6)
    assert np.isfinite(lqr.horizon) and lqr.horizon < 1e3


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_the_closed_loop_holds_the_reference_feedback(name):
    """`GoalLQR.run`: each held input is clip(u_e - K (x - x_e)) with the reference gain,
    and each state the plain RK4 of the reference dynamics from the one before."""
    from scipy.linalg import solve_discrete_are

    problem, x_e, u_e, A, B, Q, R = _reference_lqr(name)
    P = solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    lqr = build_goal_lqr(problem, DT)
    low_u, high_u = problem.system.input_limits()
    rng = np.random.default_rng(5)
    half = 0.5 * (problem.state_high - problem.state_low)
    for _ in range(3):
        x0 = x_e + rng.uniform(-0.05, 0.05, x_e.size) * half
        run = lqr.run(x0, 40, problem.constraint_box, lambda s: np.zeros(len(s), bool))
        assert len(run.inputs) >= 10, run.end
        for k, u in enumerate(run.inputs):
            e = run.states[k] - x_e
            want = np.clip(u_e - K @ e, low_u, high_u)
            # K to 1e-6 (above): the feedback to 1e-6 of the size of its terms
            np.testing.assert_allclose(u, want, rtol=0,
                                       atol=1e-6 * (np.abs(K) @ np.abs(e)).max() + 1e-12)
            step = ref.hold(REFERENCES[name], run.states[k], u, DT, 1)[-1]
            np.testing.assert_allclose(run.states[k + 1], step, rtol=1e-10, atol=1e-12)
