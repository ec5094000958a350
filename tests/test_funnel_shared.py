"""One goal funnel per query (`funnel.FunnelStream`): its extremals come from a stream of the
query's seed alone, each part is built once and the query's later solves reuse it, and the
plans stay a function of their seeds whatever ran before them."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np
import pytest

import rrtcolearn.planning.funnel as funnel_module
from rrtcolearn.anytime import solve_with_restarts
from rrtcolearn.planning.funnel import (
    AIM_DRAWS,
    AIM_POOL,
    AIM_ROUNDS,
    FUNNEL_STREAM,
    FunnelStream,
    GoalFunnel,
)
from rrtcolearn.planning.improve import shortcut
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

START, GOAL = [-np.pi, 0.0], [0.0, 0.0]
SIZE = 200  # the funnel asked for: built at every solve's start (tests/tree_cases.py)
BUDGET = 400  # iterations of a query: several solves of 20-40 iterations each


@pytest.fixture(scope="module")
def new_planner(paper_model):
    """A fresh planner on the paper's pendulum with a funnel of SIZE extremals from the start
    (the tree-hash case "pendulum": it connects through the funnel in tens of iterations)."""
    problem = PlanningProblem.create(paper_model.system, START, GOAL, 0.05)
    settings = replace(paper_model.planner_settings(), goal_connect=True, goal_funnel=SIZE)
    return lambda: RRTCoLearn(problem, paper_model.functions, settings)


def _query(planner: RRTCoLearn, seed: int, plans: list | None = None):
    """An anytime query of BUDGET iterations (restarts only); each solve's plan appended to
    ``plans``."""
    solve = planner.solve
    if plans is not None:
        def solve(termination, child, query=None, _solve=planner.solve):
            p = _solve(termination, child, query=query)
            plans.append(p)
            return p
    return solve_with_restarts(solve, TerminationCondition(None, BUDGET), seed)


def _path(plan) -> list:
    return plan.to_dict()["path"]


def test_a_querys_solves_build_its_funnel_once(new_planner, monkeypatch):
    """Counted where the funnel's extremals are integrated (independently of the stream's own
    count): one batch for the whole query, however many solves it had."""
    batches = []
    rollout = funnel_module.rollout_batch

    def counted(system, z0, *a, **k):
        batches.append(len(z0))
        return rollout(system, z0, *a, **k)
    monkeypatch.setattr(funnel_module, "rollout_batch", counted)
    planner, plans = new_planner(), []
    result = _query(planner, 1, plans)
    assert result.extra["anytime"]["solves"] == len(plans) >= 3
    # SIZE extremals (a costate for each draw here), once; the rest are the rounds of the
    # query's search for extremals through the start (`AimedSearch`: its draws and its
    # pool, each round's own), also run once for the query
    query_funnel = [b for b in batches if b not in (AIM_POOL * AIM_DRAWS, AIM_POOL)]
    assert query_funnel == [SIZE]
    assert len(batches) - 1 <= 2 * AIM_ROUNDS
    stream = planner.funnel_stream(1)
    assert stream.built == 1 and len(stream) == SIZE
    # every solve used that funnel (the same states), the later ones connecting through it too
    assert {p.extra["funnel_states"] for p in plans} == {len(stream.parts[(0, SIZE)])}
    assert sum(p.extra["connection"] == "funnel" for p in plans) >= 2


def test_the_same_seed_gives_the_same_plans_whatever_ran_before(new_planner):
    fresh, fresh_plans = new_planner(), []
    want = _query(fresh, 1, fresh_plans)
    # another query first (a funnel of its own), then this one twice: the second time every
    # part is built already
    planner = new_planner()
    _query(planner, 2)
    assert planner.funnel_stream(2).built == 1
    for _ in range(2):
        plans = []
        got = _query(planner, 1, plans)
        assert _path(got) == _path(want)
        assert [_path(p) for p in plans] == [_path(p) for p in fresh_plans]
    # a later solve of the query on its own, on a fresh planner, is the one the query ran
    # (its funnel the query's, not one of its own seed)
    child = int(np.random.SeedSequence(1).spawn(1)[0].generate_state(1)[0])
    alone = new_planner().solve(TerminationCondition(None, BUDGET), child, query=1)
    assert _path(alone) == _path(fresh_plans[1])
    assert alone.extra["funnel_states"] == fresh_plans[0].extra["funnel_states"]


def _double_integrator_funnel(rng, n: int) -> GoalFunnel:
    system = make("double_integrator")
    problem = PlanningProblem.create(system, [-1.0, 0.0], [1.0, 0.0], 0.1)
    return GoalFunnel.build(system, np.array([1.0, 0.0]), problem.goal_offset, rng,
                            n_simulations=n, time_weight=1.0, dt=0.01, max_duration=2.0,
                            max_cost=20.0, scale=system.metric_scale, tolerance=0.1)


def test_the_streams_extremals_depend_on_the_query_seed_and_their_place_only():
    """The stream's k-th extremal is the k-th draw of the generator spawned under the query's
    seed, whichever part asks for it first; parts asked for again are not built again."""
    ref = _double_integrator_funnel(
        np.random.default_rng(np.random.SeedSequence(3, spawn_key=(FUNNEL_STREAM,))), 120)
    stream = FunnelStream.of_query(3)
    later, first = stream.draws(), stream.draws()
    later.drawn = 60  # a funnel that starts at the stream's 60th extremal, built first
    b = _double_integrator_funnel(later, 60)
    a = _double_integrator_funnel(first, 60)
    assert np.array_equal(np.concatenate([a.goal_costates, b.goal_costates]),
                          ref.goal_costates)
    assert np.array_equal(np.concatenate([a.states, b.states]), ref.states)
    again = stream.draws()
    assert _double_integrator_funnel(again, 60) is a and _double_integrator_funnel(again, 60) is b
    assert stream.built == 2
    other = _double_integrator_funnel(FunnelStream.of_query(4).draws(), 60)
    assert not np.array_equal(other.goal_costates, a.goal_costates)


def test_a_later_solve_grows_the_shared_funnel_beyond_what_was_built(paper_model):
    """The automatic funnel's doublings: a connection that grows further than an earlier
    one builds only the new parts; one that grows as far builds none."""
    from rrtcolearn.planning.connections import FunnelConnection

    prob = PlanningProblem.create(paper_model.system, START, GOAL, 0.1)
    planner = RRTCoLearn(prob, paper_model.functions, paper_model.planner_settings())
    run = planner.start(np.random.default_rng(7), 7)
    stream = run.funnel
    assert stream is planner.funnel_stream(7) and stream.built == 0

    def connection():
        return FunnelConnection.build(planner.propagator, stream.draws(), run.tree.weight, 60,
                                      limit=240, grow_after=1)
    first = connection()
    first.grow()
    assert stream.built == 2 and len(stream) == 120
    second = connection()
    second.grow()
    second.grow()
    assert stream.built == 3 and len(stream) == 240
    assert all(p is q for p, q in zip(first.parts, second.parts[:2], strict=True))
    third = connection()
    for _ in range(2):
        third.grow()
    assert stream.built == 3
    assert all(p is q for p, q in zip(third.parts, second.parts, strict=True))


def test_an_anytime_query_with_its_shortcuts_is_the_same_whatever_ran_before(new_planner):
    """The improvements' search for funnel extremals through the start (`start_funnel`,
    kept by the query's stream from one solve to the next) starts afresh with each anytime
    run of the query: a second run on the same planner is the first run, bit for bit, not
    its continuation. (Two runs of one seed back to back once gave the second the first's
    search rounds: an A/B's result then followed the order, not the variant.)"""
    def run(planner):
        return solve_with_restarts(planner.solve, TerminationCondition(None, BUDGET), 1,
                                   improve=partial(shortcut, planner), in_steps=True)
    want = run(new_planner())
    # the search ran: in the solves (the funnel connection's rounds from the start) and
    # in the improvements (`start_funnel`)
    assert want.solved and want.extra["start_funnel"]["rounds"] \
        + want.extra.get("funnel_aimed", [0])[0] > 0
    planner = new_planner()
    for _ in range(2):
        got = run(planner)
        assert _path(got) == _path(want)
        assert got.extra["start_funnel"] == want.extra["start_funnel"]
