"""Random-control edges: the planner's expansion by a constant input from the input box
(plan.control_edges), re-simulated independently of the package."""

import numpy as np
import pytest
from tests.conftest import pendulum_edge
from tests.test_planner import check_plan_file

from rrtcolearn import pipeline
from rrtcolearn.config import load_config
from rrtcolearn.evaluate import resimulate
from rrtcolearn.integrate import propagate

U_MAX = 1.0


@pytest.fixture(scope="module")
def limited(tmp_path_factory):
    """The pendulum with |u| <= 1 (saturated extremals), a small dataset."""
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "generate.n_simulations=10000",
                                 "clean.k_max=1000"])
    run = tmp_path_factory.mktemp("limited")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return pipeline.fit(cfg, run)


def _with(model, **plan):
    cfg = model.config
    return cfg.model_copy(update={"plan": cfg.plan.model_copy(update=plan)})


def test_propagate_matches_a_plain_rk4(pendulum):
    x0, u, dt = np.array([0.3, -0.2]), np.array([0.7]), 0.01
    traj = propagate(pendulum, x0, u, dt, 40)
    x = x0.copy()
    for _ in range(40):  # theta'' = sin(theta) + u, written out
        def f(z):
            return np.array([z[1], np.sin(z[0]) + u[0]])
        k1 = f(x)
        k2 = f(x + 0.5 * dt * k1)
        k3 = f(x + 0.5 * dt * k2)
        k4 = f(x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(traj[-1], x, rtol=0, atol=1e-13)
    assert traj.shape == (41, 2)


def test_control_edges_on_resimulate_within_the_limit(limited):
    cfg = _with(limited, control_edges=True)
    for seed in range(3):
        p = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=seed, config=cfg,
                          time_limit=None, max_iterations=20_000)
        assert p.solved
        d = p.to_dict()
        check_plan_file(d)  # independent RK4 of both edge kinds, costs, H* = 0 on extremals
        assert p.extra["edges_by"]["control"] > 0
        for e in d["path"]:
            _, u, _ = pendulum_edge(e, d["time_weight"], d["dt"], U_MAX)
            assert np.abs(u).max() <= U_MAX + 1e-12
            if e["control"] is not None:
                assert e["max_abs_u"] == pytest.approx(abs(e["control"][0]))
        r = resimulate(limited.system, p)  # the library's own re-simulation agrees
        assert r["max_gap"] < 1e-9 and r["max_cost_gap"] < 1e-9
        assert r["path_cost"] == pytest.approx(d["path_cost"])


def test_control_edges_are_deterministic(limited):
    cfg = _with(limited, control_edges=True)
    a, b = (pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=4, config=cfg,
                          time_limit=None, max_iterations=400) for _ in range(2))
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.to_dict()["tree"] == b.to_dict()["tree"]


def test_off_is_the_learned_planner_and_auto_waits_for_a_stall(limited):
    """With control edges off, or auto before the switch, no control edge is drawn; auto
    grows the same tree as off until it switches (the switch is the only difference): it
    cannot switch within fewer than CONTROLS_AFTER iterations."""
    from rrtcolearn.planning.schedule import CONTROLS_AFTER

    off = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=1,
                        config=_with(limited, control_edges=False), time_limit=None,
                        max_iterations=CONTROLS_AFTER - 1)
    auto = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=1,
                         config=_with(limited, control_edges=None), time_limit=None,
                         max_iterations=CONTROLS_AFTER - 1)
    assert "edges_by" not in off.extra
    assert auto.extra["edges_by"]["control"] == 0
    assert off.to_dict()["tree"] == auto.to_dict()["tree"]


def test_no_input_box_no_control_edges(paper_model):
    """The unbounded pendulum has no box to draw inputs from: the learned planner only."""
    cfg = paper_model.config.model_copy(update={"plan": paper_model.config.plan.model_copy(
        update={"control_edges": True})})
    a = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=2, config=cfg,
                      time_limit=None, max_iterations=300)
    b = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=2, time_limit=None,
                      max_iterations=300)
    assert "edges_by" not in a.extra
    assert a.to_dict()["tree"] == b.to_dict()["tree"]


def test_control_edges_stay_inside_the_state_constraints(limited):
    """A control edge is cut before its first state outside the constraints."""
    cfg = _with(limited, control_edges=True, state_low=[-4 * np.pi, -2.5],
                state_high=[4 * np.pi, 2.5])
    p = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=0, config=cfg, time_limit=None,
                      max_iterations=1500)
    t = p.tree
    controls = np.flatnonzero(~np.isnan(t.controls[: t.n_nodes, 0]))
    assert controls.size > 0
    for i in controls:
        assert np.abs(t.trajectories[i][:, 1]).max() <= 2.5


def test_export_of_control_edges(limited):
    """Exported samples hold a control edge's input and no costate on it."""
    from rrtcolearn.evaluate import sample_path

    cfg = _with(limited, control_edges=True)
    d = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=0, config=cfg,
                      time_limit=None, max_iterations=20_000).to_dict()
    s = sample_path(limited.system, d)
    for i, e in enumerate(d["path"]):
        rows = np.flatnonzero(s["edge"][:-1] == i)
        if e["control"] is not None:
            assert np.isnan(s["costate"][rows]).all()
            np.testing.assert_array_equal(s["input"][rows, 0], e["control"][0])
        else:
            assert np.isfinite(s["costate"][rows]).all()
    np.testing.assert_allclose(s["state"][-1], d["path"][-1]["to"], atol=1e-9)


def test_control_edge_cost_with_two_weighted_asymmetric_inputs():
    """Two inputs, R = diag(2, 0.5), asymmetric limits: every control edge's input lies in
    the box and its cost is (w + u^T R u / 2) T, integrated independently."""
    import sympy

    from rrtcolearn.planning.problem import PlanningProblem
    from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
    from rrtcolearn.systems.symbolic import build_system

    x, y, u1, u2 = sympy.symbols("x y u1 u2", real=True)
    system = build_system(
        "weighted_two_input", [x, y], [u1, u2], [sympy.sin(y) / 2, sympy.sin(x) / 2],
        [[1, 0], [0, 1]], [[2, 0], [0, 0.5]], state_low=[-2.0, -2.0],
        state_high=[2.0, 2.0], input_low=(-1.0, -0.5), input_high=(0.5, 1.0))
    problem = PlanningProblem.create(system, [-1.0, -1.0], [1.0, 1.0], 1e-9)
    planner = RRTCoLearn(problem, None, PlannerSettings(time_weight=0.7, control_edges=True,
                                                        max_duration=1.0))
    # the random-control expansion alone (it needs no learned model)
    rng = np.random.default_rng(0)
    tree_edges = [planner.controls.control_edge(rng, np.array([-1.0, -1.0]), False)
                  for _ in range(50)]
    for edge in tree_edges:
        assert edge is not None
        traj, u, cost, steps, u_abs = edge.traj, edge.control, edge.cost, edge.steps, edge.u_abs
        assert -1.0 <= u[0] <= 0.5 and -0.5 <= u[1] <= 1.0
        assert u_abs == np.abs(u).max()
        assert cost == pytest.approx(steps * 0.01 * (0.7 + u[0] ** 2 + 0.25 * u[1] ** 2),
                                     rel=1e-12)
        np.testing.assert_allclose(traj, propagate(system, traj[0], u, 0.01, steps),
                                   rtol=0, atol=1e-12)
        assert np.all(np.abs(traj) <= 2.0)  # cut at the state constraints


def test_control_edges_avoid_obstacles(limited):
    # seeds 0 and 1 solve after 15 662 and 25 206 iterations (about 4 and 7 s of CPU): the 30 s
    # wall-clock limit this test had failed it on a loaded machine
    block = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}
    cfg = _with(limited, control_edges=True)
    for seed in range(2):
        p = pipeline.plan(limited, [-np.pi, 0], [0, 0], 0.1, seed=seed, config=cfg,
                          obstacles=[block], time_limit=None, max_iterations=40_000)
        assert p.solved
        d = p.to_dict()
        check_plan_file(d)
        for e in d["path"]:
            states, _, _ = pendulum_edge(e, d["time_weight"], d["dt"], U_MAX)
            wrapped = states.copy()
            wrapped[:, 0] -= 2 * np.pi * np.floor((states[:, 0] + 1.5 * np.pi) / (2 * np.pi))
            inside = np.all((wrapped >= block["low"]) & (wrapped <= block["high"]), axis=1)
            assert not inside.any()


@pytest.mark.parametrize("directed", [False, True])
def test_the_compiled_choice_is_the_general_one(limited, directed):
    """A goal ball without obstacles takes a compiled pass (`controls._pick_state`); the
    general code (user goal functions, obstacles) must choose the same edges from the same
    draws."""
    from rrtcolearn.planning.rrt import RRTCoLearn

    problem = pipeline.make_problem(limited.system, limited.config, [-np.pi, 0.0],
                                    [0.0, 0.0], 0.5)
    fast = RRTCoLearn(problem, limited.functions, limited.planner_settings())
    general = RRTCoLearn(problem, limited.functions, limited.planner_settings())
    general.propagator.ball = None  # (as for a user's goal function)
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    starts = np.random.default_rng(4).uniform([-np.pi, -4.0], [np.pi, 4.0], size=(300, 2))
    hits = 0
    for x0 in [*starts, np.array([0.3, 0.0]), np.array([-0.2, 0.1])]:
        a = fast.controls.control_edge(rng_a, x0, directed)
        b = general.controls.control_edge(rng_b, x0, directed)
        assert (a is None) == (b is None)
        if a is None:
            assert fast.controls.rejected == general.controls.rejected
            continue
        hits += a.hit
        np.testing.assert_array_equal(a.traj, b.traj)
        np.testing.assert_array_equal(a.control, b.control)
        assert (a.steps, a.cost, a.u_abs, a.hit, a.end_distance) == \
            (b.steps, b.cost, b.u_abs, b.hit, b.end_distance)
    assert hits > 0  # the goal test was exercised


def _tree_of(plan) -> tuple:
    t = plan.tree
    n = t.n_nodes
    return (n, plan.iterations, plan.status, t.states[:n].tobytes(), t.parents[:n].tobytes(),
            t.controls[:n].tobytes(), t.costs[:n].tobytes(), t.durations[:n].tobytes(),
            t.max_abs_u[:n].tobytes(), np.isnan(t.costates[:n]).tobytes(),
            b"".join(np.ascontiguousarray(a).tobytes() for a in t.trajectories),
            repr(sorted(plan.extra.items())))


@pytest.mark.parametrize("goal", ["ball", "function"])
def test_the_compiled_iterations_are_the_python_ones(limited, goal):
    """While random controls explore, the iterations up to the next goal-biased one run
    compiled (`RandomControls.run_batch`); with the same seed the tree, its trajectories, the
    iteration count and the outcomes are the Python loop's, for a goal ball (tested in the
    kernel) and for a user's goal function (tested after each batch, the batch cut at the
    first edge that reaches the region)."""
    from rrtcolearn.planning.rrt import RRTCoLearn
    from rrtcolearn.planning.termination import TerminationCondition

    goal_fn = None
    if goal == "function":
        def goal_fn(x):  # a ball about (0, 0) in the plain coordinates, written by a user
            return np.hypot(np.mod(x[:, 0] + np.pi, 2 * np.pi) - np.pi, x[:, 1])
    problem = pipeline.make_problem(limited.system, limited.config, [-np.pi, 0.0],
                                    [0.0, 0.0], 0.1, goal_fn=goal_fn)
    settings = limited.planner_settings(_with(limited, control_edges=True))
    compiled = RRTCoLearn(problem, limited.functions, settings)
    python = RRTCoLearn(problem, limited.functions, settings)
    python.controls.batch_constants = lambda tree: None  # every iteration in Python
    batches = []  # per compiled batch: whether it reached the goal
    run_batch = compiled.controls.run_batch

    def counted(rng, tree, progress, budget):
        pending = run_batch(rng, tree, progress, budget)
        batches.append(progress.goal_node >= 0)
        return pending
    compiled.controls.run_batch = counted
    solved = 0
    for seed in range(4):
        for budget in (40, 5000):  # stopped by the budget mid-batch, and run to the goal
            a = compiled.solve(TerminationCondition(None, budget), seed)
            b = python.solve(TerminationCondition(None, budget), seed)
            assert _tree_of(a) == _tree_of(b)
            solved += a.solved
    assert solved >= 3 and any(batches)  # some plans end in a batch's edge


def test_the_compiled_draws_are_the_python_ones(limited):
    """The learned steering's draws integrated in one compiled call (`rollout_draws_jit`)
    give what the same draws give one `rollout` at a time (a System without the kernel):
    the same rows, |u*|, codes (including draws stopped at the box), and so the same plans."""
    import dataclasses

    from rrtcolearn.integrate import rollout_draws
    from rrtcolearn.planning.rrt import RRTCoLearn
    from rrtcolearn.planning.termination import TerminationCondition

    system = limited.system
    plain = dataclasses.replace(system, rollout_draws_jit=None)
    rng = np.random.default_rng(5)
    lams = rng.uniform(-3.0, 3.0, size=(40, 2))
    steps = rng.integers(1, 400, size=40)
    box = (np.array([-10.0, -3.0]), np.array([10.0, 3.0]))
    codes_seen = set()
    for x0 in ([0.2, 0.1], [-3.0, 0.0], [2.5, -2.9]):
        a = rollout_draws(system, np.array(x0), lams, steps, 1.0, 0.01, *box, 2.0)
        b = rollout_draws(plain, np.array(x0), lams, steps, 1.0, 0.01, *box, 2.0)
        np.testing.assert_array_equal(a[3], b[3])  # codes
        codes_seen.update(a[3].tolist())
        for c in np.flatnonzero(a[3] == 0):  # kept draws: the same rows and |u*|
            ra, rb = slice(a[2][c], a[2][c + 1]), slice(b[2][c], b[2][c + 1])
            np.testing.assert_array_equal(a[0][ra], b[0][rb])
            np.testing.assert_array_equal(a[1][ra], b[1][rb])
    assert {0, 1} <= codes_seen
    problem = pipeline.make_problem(system, limited.config, [-np.pi, 0.0], [0.0, 0.0], 0.1)
    fast = RRTCoLearn(problem, limited.functions, limited.planner_settings())
    slow = RRTCoLearn(dataclasses.replace(problem, system=plain), limited.functions,
                      limited.planner_settings())
    for seed in range(3):
        a = fast.solve(TerminationCondition(None, 3000), seed)
        b = slow.solve(TerminationCondition(None, 3000), seed)
        assert _tree_of(a) == _tree_of(b)


def test_a_solve_compiles_nothing_while_its_clock_runs(limited):
    """`load_kernels` (a fit, a load, and a solve before its clock) loads every kernel a plan
    calls with the very argument types the plan passes: plans that explore with random
    controls and try the LQR connection add no compiled signature."""
    from rrtcolearn.planning.rrt import load_kernels

    sys = limited.system
    load_kernels(sys, explore=True, lqr=True)
    kernels = ("costate_from_params_jit", "rollout_jit", "input_max_abs_jit", "propagate_jit",
               "rollout_batch_jit", "rollout_draws_jit", "explore_jit", "closed_loop_jit")
    from rrtcolearn.planning import nearest, propagator

    # the planner's own compiled functions, loaded by the model's throwaway solve
    own = {"_summarise_draws": propagator._summarise_draws, "_sqdists": nearest._sqdists,
           "_least": nearest._least}

    def signatures():
        return {**{k: len(getattr(sys, k).signatures) for k in kernels},
                **{k: len(f.signatures) for k, f in own.items()}}

    before = signatures()
    assert all(before.values()), before
    cfg = _with(limited, control_edges=True, goal_lqr=True)
    for seed in range(3):
        p = pipeline.plan(limited, [-np.pi, 0.0], [0.0, 0.0], 0.1, seed, config=cfg,
                          max_iterations=3000, time_limit=None)
        assert p.extra["goal_lqr"]["tries"] > 0
    assert signatures() == before


def test_a_limit_that_stops_a_growing_tree_is_named_as_the_cause():
    from rrtcolearn.planning.diagnosis import diagnose

    line = diagnose({"added": 1, "out_of_reach": 1}, False, 2, False, (2.0, 1.9))
    assert line.startswith("limit reached after 2 iterations with 2 nodes")
    assert "the tree was still growing — raise the time or iteration limit" in line
    assert "most common rejection: out of reach, in 1" in line
    # no rejection held most iterations back: still the limit
    line = diagnose({"added": 8, "invalid_query": 5, "out_of_reach": 33}, False, 10, False)
    assert line.endswith("17% of the iterations added a node — raise the time or iteration "
                         "limit (most common rejection: invalid query, in 5)")
    # a rejection that stopped most iterations is named with its advice
    line = diagnose({"added": 20, "invalid_query": 38, "out_of_reach": 9}, False, 10, False)
    assert "57% of the iterations: invalid query — the validity model V" in line
    line = diagnose({"invalid_query": 2000}, True, 1, False)
    assert line.startswith("the tree stopped growing (1 node")
    assert diagnose({}, False, 1, False).startswith("no iteration ran")


def test_a_planner_api_plan_at_the_models_own_limit_exports(limited, tmp_path):
    """The Planner API takes the problem every peer takes, u_max at the model's own limit
    included; its plan file (no configuration recorded) exports with --system, the limits
    taken from the box the file records."""
    from typer.testing import CliRunner

    from rrtcolearn import planners
    from rrtcolearn.cli import app
    from rrtcolearn.planning.problem import PlanningProblem
    from rrtcolearn.planning.termination import TerminationCondition

    planner = planners.make("rrtcolearn", model=limited)
    problem = PlanningProblem.create(limited.system, [-np.pi, 0.0], [0.0, 0.0], 0.1,
                                     u_max=U_MAX)
    assert planner.supports(problem) is None
    other = PlanningProblem.create(limited.system, [-np.pi, 0.0], [0.0, 0.0], 0.1, u_max=0.5)
    assert "not 0.5" in planner.supports(other)
    p = planner.solve(problem, TerminationCondition(None, 20_000), seed=0)
    assert p.solved and "config" not in p.extra
    path = tmp_path / "api.json"
    pipeline.write_plan(p, path)
    result = CliRunner().invoke(app, ["export", str(path)])
    assert result.exit_code == 2 and "--system" in result.output
    result = CliRunner().invoke(app, ["export", str(path), "--system", "pendulum"])
    assert result.exit_code == 0, result.output
