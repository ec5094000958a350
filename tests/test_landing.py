"""Learned edges that land (`planning.learned.LearnedSteering.refine`) and the share of a path's
duration by kind of edge (`Plan.duration_by`, the plan file's ``duration_by``).

The refined edges are re-simulated by the test's own RK4 (tests/conftest.py), not the
package's integrator."""

from dataclasses import replace

import numpy as np
import pytest
from tests.conftest import pendulum_edge
from tests.tree_cases import CASES, fit_model, plan_case

from rrtcolearn import pipeline
from rrtcolearn.planning.learned import LAND_FRACTION
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

_CASES = {c.name: c for c in CASES}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("landing_models")
    return {name: fit_model(_CASES[name], root / name) for name in ("pendulum", "pendulum_u1")}


def _hand_shares(d: dict) -> tuple[float, float]:
    """Shares of the path's duration made by extremals and by held inputs, summed by hand
    from the plan file's edges."""
    total = sum(e["duration"] for e in d["path"])
    extremal = sum(e["duration"] for e in d["path"] if e["control"] is None)
    return extremal / total, (total - extremal) / total


@pytest.mark.parametrize("name", ["pendulum", "pendulum_u1"])
def test_duration_shares_sum_to_one_and_match_a_hand_sum(models, name):
    plan = plan_case(_CASES[name], models[name])
    assert plan.solved
    d = plan.to_dict()
    shares = d["duration_by"]
    assert sum(shares.values()) == pytest.approx(1.0, abs=1e-12)
    extremal, held = _hand_shares(d)
    # learned extremals and shooting/funnel extremals have a costate; random controls and
    # the LQR chain hold inputs
    assert shares.get("learned", 0) + shares.get("shooting", 0) + shares.get("funnel", 0) \
        == pytest.approx(extremal, abs=1e-12)
    assert shares.get("control", 0) + shares.get("lqr", 0) == pytest.approx(held, abs=1e-12)
    total = sum(e["duration"] for e in d["path"])
    conn = d["connection"]
    assert conn is not None
    if conn in ("shooting", "funnel"):  # one edge, the last
        assert shares[conn] == pytest.approx(d["path"][-1]["duration"] / total, abs=1e-12)
    else:  # the LQR chain: the last edges, held inputs
        assert d["path"][-1]["control"] is not None and shares["lqr"] > 0


def _planner(model, refine: int, u_max=None):
    cfg = model.config
    problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], [0.0, 0.0], 0.05,
                                    u_max=u_max)
    settings = replace(model.planner_settings(cfg), refine_iterations=refine)
    return RRTCoLearn(problem, model.functions, settings)


def _refined_plan(model, seed: int):
    planner = _planner(model, 6)
    return planner, planner.solve(TerminationCondition(None, 3000), seed)


def test_refined_edges_land_and_resimulate(models):
    model = models["pendulum"]
    planner, plan = _refined_plan(model, 3)
    landing = plan.extra["landing"]
    assert landing["landed"] > 0 and landing["refined"] >= landing["landed"]
    tol = LAND_FRACTION * 0.05
    assert planner.learned.land_tolerance == tol
    # the landed edges: every learned edge whose end is within the tolerance of its aim is
    # checked independently below through the plan file (each path edge re-simulates)
    d = plan.to_dict()
    w, dt = d["time_weight"], d["dt"]
    for e in d["path"]:
        states, _, cost = pendulum_edge(e, w, dt)
        np.testing.assert_allclose(states[-1], e["to"], atol=1e-6)
        assert cost == pytest.approx(e["cost"], rel=1e-9, abs=1e-12)
    errors = np.asarray(planner.learned.errors)
    assert (errors <= tol).sum() >= landing["landed"]


def test_refine_lands_on_a_target_within_tolerance(models):
    """One learned edge, refined, against an independent RK4 of its costate and duration."""
    model = models["pendulum"]
    planner = _planner(model, 8)
    run = planner.start(np.random.default_rng(0))
    rng = np.random.default_rng(5)
    steering = planner.learned
    landed = 0
    for _ in range(200):
        target = rng.uniform(model.system.state_low, model.system.state_high)
        parent, edge, aim = steering.propose(rng, run.tree, target, False)
        if edge is None:
            continue
        x0 = run.tree.states[parent]
        new = steering.refine(x0, edge, aim, False)
        run.tree.add(parent, new)  # the tree grows, as in a plan
        if new is edge:
            continue
        landed += 1
        e = {"from": x0.tolist(), "costate": new.costate.tolist(), "control": None,
             "duration": new.steps * planner.settings.dt}
        states, _, cost = pendulum_edge(e, planner.settings.time_weight, planner.settings.dt)
        gap = states[-1] - aim
        gap[0] = np.mod(gap[0] + np.pi, 2 * np.pi) - np.pi
        assert np.linalg.norm(gap) <= steering.land_tolerance + 1e-9
        assert cost == pytest.approx(new.cost, rel=1e-9)
    assert landed >= 10


def test_refinement_is_deterministic_per_seed(models):
    model = models["pendulum"]
    a, b = (_refined_plan(model, 4)[1] for _ in range(2))
    n = a.tree.n_nodes
    assert n == b.tree.n_nodes and a.iterations == b.iterations
    assert np.array_equal(a.tree.states[:n], b.tree.states[:n])
    assert a.extra["landing"] == b.extra["landing"]
    assert a.extra["duration_by"] == b.extra["duration_by"]
