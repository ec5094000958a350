"""The planner's parts alone and plugged in: each steering strategy against a tree and a
problem, and a goal connection written here, outside the package, that the loop runs
without a change to it (`RRTCoLearn(..., connections=...)`)."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import pendulum_edge
from tests.test_planner import check_plan_file

from rrtcolearn import pipeline
from rrtcolearn.config import load_config
from rrtcolearn.integrate import propagate
from rrtcolearn.planning.contracts import OUTCOMES, Edge, GrowingTree
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

U_MAX = 1.0


@pytest.fixture(scope="module")
def limited(tmp_path_factory):
    """The pendulum with |u| <= 1, a small dataset."""
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "generate.n_simulations=3000",
                                 "clean.k_max=300"])
    run = tmp_path_factory.mktemp("parts")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return pipeline.fit(cfg, run)


def _planner(model, connections=(), **plan):
    cfg = model.config
    cfg = cfg.model_copy(update={"plan": cfg.plan.model_copy(update=plan)})
    problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], [0.0, 0.0], 0.05)
    return RRTCoLearn(problem, model.functions, model.planner_settings(cfg), connections)


class OneStepConnection:
    """Connect by one constant input when the goal is that close: from the untried node
    nearest the goal (the goal test's distance), each input of a grid over the input box
    held for up to ``steps`` RK4 steps; the first held input whose states enter the goal
    region (within the state box, clear of obstacles) is the edge, cut there. Written
    against `contracts.Connection` only."""

    name = "one_step"

    def __init__(self, planner: RRTCoLearn, steps: int = 30, inputs: int = 21):
        self.propagator = planner.propagator
        self.steps = steps
        low, high = self.propagator.control_box
        self.grid = np.linspace(low, high, inputs)  # (inputs, m)
        self.tried: set[int] = set()
        self.tries = 0

    def connect(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None:
        prop = self.propagator
        prob, dt = prop.problem, prop.settings.dt
        dist = prob.goal_distance(tree.states)
        dist[list(self.tried)] = np.inf
        node = int(np.argmin(dist))
        if not np.isfinite(dist[node]):
            return None
        self.tried.add(node)
        self.tries += 1
        x0 = tree.states[node]
        for u in self.grid:
            states = propagate(prob.system, x0, u, dt, self.steps, *prop.box)
            inside = np.all((states >= prop.box[0]) & (states <= prop.box[1]), axis=1)
            if prob.validity:
                inside &= prob.validity(states)
            if not inside.all():
                states = states[: int(np.argmin(inside))]  # the valid prefix
            hits = np.flatnonzero(prop.goal_mask(states[1:]))
            if hits.size:
                k = int(hits[0]) + 1
                return node, [Edge(states[: k + 1], k, k * dt * prop.hold_rate(u),
                                   float(np.abs(u).max()), True, control=u.copy())]
        return None

    def report(self) -> dict:
        return {"one_step": {"tries": self.tries}}

    def note(self) -> str | None:
        return None


def test_a_connection_written_outside_plugs_into_the_loop(limited):
    """The learned steering alone (every planner connection off) with the one-step
    connection plugged in: plans finish by its edge, a held input that re-simulates
    independently; up to that edge the tree is the one the planner grows without it."""
    off = {"goal_connect": False, "goal_funnel": 0, "goal_lqr": False, "control_edges": False}
    plugged = _planner(limited, (OneStepConnection,), **off)
    alone = _planner(limited, **off)
    finished = 0
    for seed in range(6):
        p = plugged.solve(TerminationCondition(None, 1500), seed)
        if p.extra["connection"] is None:  # unsolved, or solved by the steering itself
            continue
        finished += 1
        assert p.extra["connection"] == "one_step" and p.extra["goal_connected"] and p.solved
        assert p.extra["one_step"]["tries"] >= 1
        last = p.path_nodes[-1]
        u = p.tree.controls[last]
        assert np.isfinite(u).all() and abs(u[0]) <= U_MAX  # a held input ends the path
        d = p.to_dict()
        check_plan_file(d)  # independent RK4 of every edge, costs, H* = 0 on extremals
        states, inputs, _ = pendulum_edge(d["path"][-1], d["time_weight"], d["dt"], U_MAX)
        assert np.all(inputs == u[0])
        ang = np.mod(states[-1, 0] + np.pi, 2 * np.pi) - np.pi
        assert np.hypot(ang, states[-1, 1]) <= 0.05 + 1e-12  # ends in the goal ball
        # the tree before the connection is the planner's own: the same seed without the
        # connection grows the same nodes up to that iteration
        # (it runs that iteration's expansion, which the connection cut short)
        b = alone.solve(TerminationCondition(None, p.iterations), seed)
        m = p.tree.n_nodes - 1  # the nodes before the connection's edge
        assert b.tree.n_nodes in (m, m + 1)
        np.testing.assert_array_equal(b.tree.states[:m], p.tree.states[:m])
    assert finished >= 3


def test_each_steering_strategy_alone(limited):
    """Against a tree and a problem, without the loop: the learned steering and random
    controls each propose (parent, edge) with the edge starting at the parent's state and
    lasting its steps, or no edge with a reason from OUTCOMES; they add nothing to the
    tree."""
    planner = _planner(limited, control_edges=True)
    rng = np.random.default_rng(0)
    run = planner.start(rng)
    tree = run.tree
    made = {"learned": 0, "control": 0}
    for steering in (planner.learned, planner.controls):
        planner.controls.batch = None  # the random-control edges here, not in a batch
        for i in range(60):
            target = rng.uniform(limited.system.state_low, limited.system.state_high)
            parent, edge = steering.steer(rng, tree, target, to_goal=i % 5 == 0)
            assert tree.data.n_nodes == 1 + made["learned"] + made["control"]
            if edge is None:
                assert steering.rejected in OUTCOMES
                continue
            np.testing.assert_array_equal(edge.traj[0, :2], tree.states[parent])
            assert len(edge.traj) == edge.steps + 1
            assert (edge.control is None) == (steering.kind == "learned")
            tree.add(parent, edge)
            made[steering.kind] += 1
    assert made["learned"] > 0 and made["control"] > 0


def test_cost_to_come_by_hand():
    """`PlannerData.cost_to_come`: each node's sum of edge costs from the root, by hand on a
    branching tree, extended after nodes are added past a first call."""
    from rrtcolearn.planning.tree import PlannerData

    tree = PlannerData(np.zeros(2), 1, capacity=2)
    nan2, nan1 = np.full(2, np.nan), np.full(1, np.nan)
    for parent, cost in ((0, 1.5), (0, 2.0), (1, 0.25)):  # nodes 1, 2, 3
        tree.add(np.zeros(2), parent, nan2, nan1, 1.0, cost, np.zeros((2, 2)), 0.0)
    np.testing.assert_array_equal(tree.cost_to_come(np.array([3, 0, 2, 1])),
                                  [1.75, 0.0, 2.0, 1.5])
    for parent, cost in ((3, 4.0), (2, 0.5), (4, 1.0)):  # nodes 4, 5, 6 (the arrays grow)
        tree.add(np.zeros(2), parent, nan2, nan1, 1.0, cost, np.zeros((2, 2)), 0.0)
    np.testing.assert_array_equal(tree.cost_to_come(np.arange(7)),
                                  [0.0, 1.5, 2.0, 1.75, 5.75, 2.5, 6.75])


def test_an_extremal_added_on_a_row_a_compiled_batch_wrote_has_no_control():
    """A compiled random-control batch writes its draws' rows in place (`PlannerData.reserve`)
    and may leave a row written but not kept (sparse_rrt's acrobot, seed 0: the row after
    the first solve's last node). An extremal the anytime shortcuts then add on that row
    had kept the row's held input: the plan file called it a control edge, and its replay
    held that input for the extremal's 5.8 s (it ended 51 from the goal instead of 1.5)."""
    from rrtcolearn.planning.tree import PlannerData

    tree = PlannerData(np.zeros(2), 1, capacity=2)
    tree.reserve(3)
    tree.controls[1] = 0.59  # a batch's row, not kept (n_nodes stays 1)
    costate, params = np.array([0.5, -1.0]), np.array([2.0])
    node = tree.add(np.ones(2), 0, costate, params, 1.0, 0.7, np.zeros((2, 2)), 0.3)
    assert node == 1 and np.isnan(tree.controls[1]).all() and tree.kind(1) == "learned"
    node = tree.add(np.ones(2), 1, np.full(2, np.nan), np.full(1, np.nan), 1.0, 0.7,
                    np.zeros((2, 2)), 0.3, control=np.array([-0.25]))
    assert tree.controls[node].tolist() == [-0.25]


@pytest.mark.parametrize("on", [False, True])
def test_parent_cost_to_come_ranks_by_the_trees_cost_to_come(limited, monkeypatch, on):
    """With ``plan.parent_cost_to_come`` the learned steering ranks its candidates by J plus
    each candidate's cost-to-come, as the tree has it (checked against sums of edge costs
    along `path_to` on the final tree, whose edges do not change); without it, by J alone
    (no offset). The ranking itself is `best_valid`'s (tests/test_learn.py)."""
    import sys

    import rrtcolearn.planning.learned as learned
    from rrtcolearn.planning.tree import PlannerData

    given, made = [], []
    real_best, real_ctc = learned.best_valid, PlannerData.cost_to_come

    def best_valid(functions, X, offset=None):
        given.append((X.copy(), offset))
        return real_best(functions, X, offset)

    def cost_to_come(self, nodes):
        out = real_ctc(self, nodes)
        # the learned steering's calls (the goal funnel's connection ranks its nodes by
        # cost to come too, whatever the setting)
        if sys._getframe(1).f_globals["__name__"] == learned.__name__:
            made.append((self, nodes.copy(), out))
        return out

    monkeypatch.setattr(learned, "best_valid", best_valid)
    monkeypatch.setattr(PlannerData, "cost_to_come", cost_to_come)
    plan = _planner(limited, parent_cost_to_come=on, control_edges=False).solve(
        TerminationCondition(None, 300), 3)
    assert len(given) > 50
    if not on:
        assert all(o is None for _, o in given) and not made
        return
    assert len(made) == len(given)
    tree, n = plan.tree, limited.system.n_states
    for (X, offset), (data, nodes, out) in zip(given, made, strict=True):
        assert offset is out and data is tree
        # the offsets are the query rows' own start nodes (their states, whole turns apart)
        gap = X[:, :n] - tree.states[nodes]
        np.testing.assert_allclose(np.mod(gap[:, 0] + np.pi, 2 * np.pi) - np.pi, 0.0,
                                   atol=1e-9)
        np.testing.assert_allclose(gap[:, 1:], 0.0, atol=1e-12)
        want = [sum(tree.costs[i] for i in tree.path_to(int(k))[1:]) for k in nodes]
        np.testing.assert_allclose(out, want, rtol=1e-12)
    assert max(float(o.max()) for _, o in given if o.size) > 0.0  # nodes below the root


def test_the_allowance_spaces_attempts_in_vain_ever_wider():
    """(gains + 1) / (tries + 1) of an attempt per goal-biased iteration, no gains: the k-th
    attempt comes at call k (k + 1) / 2 when a node is there at every call (counted here by
    brute force over the calls), and idle calls bank at most one attempt."""
    from rrtcolearn.planning.schedule import Allowance

    a, calls = Allowance(), []
    for call in range(1, 60):
        a.accrue()
        if a.take():
            calls.append(call)
    assert calls == [k * (k + 1) // 2 for k in range(1, 11)]
    idle = Allowance(tries=5, waited=0)
    for _ in range(100):  # no node to try: nothing taken
        idle.accrue()
    assert idle.take() and not idle.take()


def test_the_automatic_funnel_switches_on_with_shooting_and_not_while_exploring():
    from rrtcolearn.planning.contracts import Progress
    from rrtcolearn.planning.schedule import CONNECT_AFTER, Schedule
    from rrtcolearn.planning.settings import PlannerSettings

    auto = PlannerSettings()  # goal_connect, goal_funnel, goal_lqr: None (the planner's)
    on = {"shooting": None, "funnel": None, "lqr": None}
    for exploring, want in ((False, ["lqr", "shooting", "funnel"]), (True, ["lqr"])):
        s = Schedule.start(auto, controls=exploring, learned=True, can_connect=True)
        s.exploring = exploring
        assert s.connections_due(Progress(1.0, iterations=7, since_nearer=CONNECT_AFTER - 1),
                                 on) == []
        assert s.connections_due(Progress(1.0, iterations=8, since_nearer=CONNECT_AFTER),
                                 on) == want
        assert s.switched == dict.fromkeys(want, 8)
    # an explicit funnel size or 0 (off) leaves it to the settings
    for size in (0, 500):
        s = Schedule.start(PlannerSettings(goal_funnel=size), controls=False, learned=True,
                           can_connect=True)
        assert "funnel" not in s.connections_due(
            Progress(1.0, since_nearer=CONNECT_AFTER), on)


def test_without_an_lqr_connection_shooting_and_the_funnel_switch_on_while_exploring():
    """Where no LQR connection reaches the goal region, nothing but shooting and the funnel
    connects: they switch on when the tree stalls even while random controls explore."""
    from rrtcolearn.planning.contracts import Progress
    from rrtcolearn.planning.schedule import CONNECT_AFTER, Schedule
    from rrtcolearn.planning.settings import PlannerSettings

    on = {"shooting": None, "funnel": None, "lqr": None}
    for goal_lqr, want in ((True, ["lqr"]), (False, ["lqr", "shooting", "funnel"])):
        s = Schedule.start(PlannerSettings(), controls=True, learned=True, can_connect=True,
                           goal_lqr=goal_lqr)
        s.exploring = True
        assert s.connections_due(Progress(1.0, iterations=8, since_nearer=CONNECT_AFTER),
                                 on) == want
    # shooting set off stays off
    s = Schedule.start(PlannerSettings(goal_connect=False), controls=True, learned=True,
                       can_connect=True, goal_lqr=False)
    s.exploring = True
    assert "shooting" not in s.connections_due(Progress(1.0, since_nearer=CONNECT_AFTER), on)


def test_a_derived_funnel_runs_to_the_box_where_the_goal_has_no_lqr_connection(limited):
    """Into a goal that is no equilibrium under |u| <= 1 (the pendulum held 1 rad from upright needs
    a torque of about 8) the planner has no LQR connection; its derived goal funnel then
    runs each extremal for up to generate.max_duration with no cost bound, and its states
    lie farther from the goal in time than the data's longest extremal. A funnel duration
    the user gives is kept; a goal with an LQR connection keeps the data's funnel."""
    from dataclasses import replace

    from rrtcolearn.planning.settings import PlannerSettings

    model = limited
    cfg = model.config
    settings = model.planner_settings(cfg)
    # the fit recorded the derived duration; the planner derives it again (None here)
    assert cfg.plan.funnel_duration == model.max_duration
    assert "plan.funnel_duration" in cfg.derived and settings.funnel_duration is None
    given = cfg.model_copy(update={"plan": cfg.plan.model_copy(update={
        "funnel_duration": 1.25})})
    assert model.planner_settings(given).funnel_duration == 1.25

    def planner(goal, s):
        problem = pipeline.make_problem(model.system, cfg, [-np.pi, 0.0], goal, 0.05)
        return RRTCoLearn(problem, model.functions, s)

    held = planner([0.0, 0.0], settings)
    assert held.goal_lqr_off is None
    assert held.funnel_reach == (model.max_duration, cfg.generate.max_cost)
    off = planner([-1.0, 0.0], settings)
    assert off.goal_lqr_off is not None and "equilibrium" in off.goal_lqr_off
    assert off.funnel_reach == (cfg.generate.max_duration, np.inf)
    assert planner([-1.0, 0.0], replace(settings, funnel_duration=1.25)).funnel_reach == \
        (1.25, cfg.generate.max_cost)
    # turning the connection off is no goal without one: the data's funnel
    assert planner([0.0, 0.0], replace(settings, goal_lqr=False)).funnel_reach == \
        held.funnel_reach
    assert PlannerSettings.from_config(cfg, max_duration=2 * model.max_duration
                                       ).funnel_duration == model.max_duration
    # the funnel itself: extremals longer than the data's, stopped only by the box
    funnel = off.connection("funnel", off.funnel_stream(0), off.start(
        np.random.default_rng(0), 0).tree, 300)
    part = funnel.parts[0]
    assert funnel.duration == cfg.generate.max_duration and funnel.own
    assert funnel.report()["funnel_duration"] == funnel.duration
    assert "funnel_duration" not in held.connection("funnel", held.funnel_stream(0), held.start(
        np.random.default_rng(0), 0).tree, 300).report()
    assert part.steps.max() * part.dt > 1.5 * model.max_duration
    narrow = held.connection("funnel", held.funnel_stream(0), held.start(
        np.random.default_rng(0), 0).tree, 300)
    assert not narrow.own  # (the chain along a funnel state's own extremal: not tried here)
    assert narrow.parts[0].steps.max() * narrow.parts[0].dt <= model.max_duration + 1e-9


def test_into_a_goal_without_an_lqr_connection_the_funnel_connects_and_resimulates(limited):
    """The pendulum at |u| <= 1 into 1 rad from upright at rest (no equilibrium: no LQR
    connection): with random controls exploring, shooting and the funnel switch on when the
    tree stalls, and a path through the funnel re-simulates by an independent RK4 into the
    goal ball, its extremals on H* = 0 under the saturated input."""
    goal = np.array([-1.0, 0.0])
    problem = pipeline.make_problem(limited.system, limited.config, [-np.pi, 0.0], goal, 0.05)
    planner = RRTCoLearn(problem, limited.functions, limited.planner_settings(limited.config))
    through = []
    for seed in range(6):
        p = planner.solve(TerminationCondition(None, 3000), seed)
        switched = p.extra["connections_switched_on"]
        if "funnel" in switched:
            # switched on while random controls explored (they switch on first)
            assert switched["funnel"] >= switched["controls"] and "shooting" in switched
            assert p.extra["funnel_duration"] == limited.config.generate.max_duration
        if p.solved and p.extra.get("connection") in ("funnel", "shooting"):
            through.append(p)
    assert through, "no path connected through shooting or the funnel"
    for p in through:
        d = p.to_dict()
        check_plan_file(d)
        states, _, _ = pendulum_edge(d["path"][-1], d["time_weight"], d["dt"], U_MAX)
        ang = np.mod(states[-1, 0] - goal[0] + np.pi, 2 * np.pi) - np.pi
        assert np.hypot(ang, states[-1, 1]) <= 0.05 + 1e-9
