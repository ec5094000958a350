"""The learned steering's cost check (`planning.learned.data_cost_ratio`,
`LearnedSteering.costly_edge`): a learned edge far dearer than the learned J between its own
ends is rejected, the bound a quantile of the data's own leave-one-out ratios.

The references are computed by hand (a six-segment dataset on a line) or, for a planner's
edges, from J queried directly (`LearnedFunctions.query`)."""

import copy
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from tests.tree_cases import CASES, fit_model

from rrtcolearn import pipeline
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.planning.contracts import Edge
from rrtcolearn.planning.learned import LearnedSteering, data_cost_ratio
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

# six segments from the origin to (t, 0): distinct gaps, so every nearest-three is unique
_ENDS = np.array([0.0, 1.0, 3.0, 7.0, 12.0, 20.0])
_COSTS = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
# by hand: each segment's cost over the mean cost of its three nearest other segments
# t=0: (1,3,7) -> 3; t=1: (0,3,7) -> 8/3; t=3: (1,0,7) -> 7/3; t=7: (3,12,1) -> 10/3;
# t=12: (7,20,3) -> 13/3; t=20: (12,7,3) -> 4
_RATIOS = np.array([1 / 3, 3 / 4, 9 / 7, 6 / 5, 15 / 13, 3 / 2])


@pytest.fixture(scope="module")
def line_model():
    n = len(_ENDS)
    x0 = np.zeros((n, 2))
    x1 = np.column_stack([_ENDS, np.zeros(n)])
    data = Dataset(x0=x0, x1=x1, cost=_COSTS, params=np.zeros((n, 1)),
                   duration=np.ones(n), costate=np.zeros((n, 2)), simulation=np.arange(n))
    return LearnedFunctions(validity_threshold=1e3, periodic=False).fit(data,
                                                                        make("pendulum"))


def test_data_cost_ratio_is_the_quantile_of_hand_computed_leave_one_out_ratios(line_model):
    assert data_cost_ratio(line_model, 1.0) == pytest.approx(1.5, rel=1e-12)
    assert data_cost_ratio(line_model, 0.5) == pytest.approx((15 / 13 + 6 / 5) / 2, rel=1e-12)
    for q in (0.0, 0.25, 0.9, 0.99):
        assert data_cost_ratio(line_model, q) == pytest.approx(np.quantile(_RATIOS, q),
                                                               rel=1e-12)


def test_costly_edge_against_the_hand_computed_bound(line_model):
    # J from the origin to (7, 0): the segments to 7, 3 and 12 (distances 0, 4, 5), costs
    # 4, 3, 5 -> 4; to the aim (20, 0): 20, 12, 7 -> 5; with a ratio of 1.5 the bound is 6
    steering = SimpleNamespace(cost_ratio=1.5, model=line_model)
    x0, shift, aim = np.zeros(2), np.zeros(2), np.array([20.0, 0.0])

    def edge(cost):
        traj = np.array([[0.0, 0.0, 0.0, 0.0, 0.0], [7.0, 0.0, 0.0, 0.0, cost]])
        return Edge(traj, 1, cost, 0.0, False, np.zeros(2), np.zeros(2))

    assert not LearnedSteering.costly_edge(steering, x0, shift, edge(6.0), aim)
    assert LearnedSteering.costly_edge(steering, x0, shift, edge(6.0 + 1e-9), aim)
    assert not LearnedSteering.costly_edge(steering, x0, shift, edge(0.1), aim)
    # J from the origin to an aim at (1, 0): the segments to 1, 0 and 3, costs 2, 1, 3 -> 2;
    # the bound is 1.5 times the lesser J, 3, whatever the edge's own ends
    near = np.array([1.0, 0.0])
    assert not LearnedSteering.costly_edge(steering, x0, shift, edge(3.0), near)
    assert LearnedSteering.costly_edge(steering, x0, shift, edge(3.0 + 1e-9), near)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("cost_models")
    return {c.name: fit_model(c, root / c.name) for c in CASES
            if c.name in ("pendulum", "cartpole")}


@pytest.fixture(scope="module")
def pendulum(models):
    return models["pendulum"]


def _planner(model, ratio):
    start, goal = pipeline.query_states(model.config, model.system)
    problem = pipeline.make_problem(model.system, model.config, start, goal,
                                    model.config.plan.goal_tolerance)
    settings = replace(model.planner_settings(model.config), edge_cost_ratio=ratio)
    return RRTCoLearn(problem, model.functions, settings)


# the pendulum: one steering parameter, one draw (the paper's); the cart-pole: 16 draws,
# the one nearest the aim kept (`LearnedSteering._draws`)
@pytest.mark.parametrize("name", ["pendulum", "cartpole"])
def test_steering_keeps_the_nearest_draw_within_the_bound(models, name):
    """Two steerings on the same tree and draws, with the check off and on: every edge the
    check lets through is within the bound (the ratio times the lesser J between its ends
    and from its start to its aim, J queried here directly); where the unchecked edge is
    within it, both are the same edge."""
    model = models[name]
    rule, off = _planner(model, "data"), _planner(model, 0.0)
    ratio = data_cost_ratio(model.functions)
    assert rule.learned.cost_ratio == ratio and ratio > 1.0
    tree, rng = rule.start(np.random.default_rng(0)).tree, np.random.default_rng(11)
    sys_ = model.system
    n = sys_.n_states

    def bound(parent, edge, aim):
        x0, sh = tree.states[parent] + tree.shifts[parent], tree.shifts[parent]
        q = np.stack([np.concatenate([x0, edge.traj[-1, :n] + sh]),
                      np.concatenate([x0, aim + sh])])
        return ratio * float(model.functions.query(q)[0].min())

    same = other = rejected = 0
    for _ in range(400):
        target = rng.uniform(sys_.state_low, sys_.state_high)
        twin = copy.deepcopy(rng)
        parent, unchecked, aim = off.learned.propose(twin, tree, target, False)
        got_parent, edge, got_aim = rule.learned.propose(rng, tree, target, False)
        assert got_parent == parent
        if unchecked is None:
            assert edge is None
            continue
        np.testing.assert_array_equal(got_aim, aim)
        if edge is None:
            assert rule.learned.rejected == "invalid_query"
            assert unchecked.cost > bound(parent, unchecked, aim)
            rejected += 1
            continue
        assert edge.cost <= bound(parent, edge, aim)
        if unchecked.cost <= bound(parent, unchecked, aim):
            np.testing.assert_array_equal(edge.traj, unchecked.traj)
            same += 1
        else:
            other += 1
        tree.add(parent, edge)
    assert same > 0 and other + rejected > 0
    assert rule.learned.costly[0] >= other + rejected


def test_zero_ratio_switches_the_check_off_and_a_tiny_one_rejects_every_edge(pendulum):
    off = _planner(pendulum, 0.0).solve(TerminationCondition(None, 300), 1)
    assert off.extra["landing"]["costly"] == 0 and off.extra["landing"]["edges"] > 0
    tiny = _planner(pendulum, 1e-12).solve(TerminationCondition(None, 300), 1)
    assert tiny.extra["landing"]["edges"] == 0 and tiny.extra["landing"]["costly"] > 0
    assert tiny.extra["landing"]["guessed"] == 0
