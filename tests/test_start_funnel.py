"""Funnel extremals through the start (`funnel.AimedSearch`, `improve.start_funnel`): a random
local search over the goal funnel's goal costates brings an extremal from the goal ever
nearer the query's start, and the funnel connection along it gives a path from the start
that replaces a dearer one. Checked with Pontryagin's equations on the textbook acrobot and
a plain RK4 written in the suite (`tests/references.py`), not the system's kernels."""

from __future__ import annotations

import types
from itertools import pairwise

import numpy as np
import pytest
from tests import references
from tests.references import rk4

from rrtcolearn.planning import improve
from rrtcolearn.planning.contracts import Edge, add_edge
from rrtcolearn.planning.funnel import AIM_ROUNDS, FunnelStream, GoalFunnel
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.rrt import PlannerSettings
from rrtcolearn.planning.tree import Plan, PlannerData
from rrtcolearn.systems import make

DT = 0.01
DURATION = 6.0  # the funnel's extremals: a swing-up lasts about 5 s
GOAL = np.array([np.pi, 0.0, 0.0, 0.0])  # upright
START = np.zeros(4)  # hanging
TOLERANCE = 0.3
QUERY = 1  # measured: within 0.036 of the start after the rounds, a path of cost 35.8


@pytest.fixture(scope="module")
def acrobot():
    system = make("acrobot")
    problem = PlanningProblem.create(system, START, GOAL, TOLERANCE, wrap_goal=True)
    return system, problem


def _stream(system, problem, query: int = QUERY) -> FunnelStream:
    """The query's funnel stream with its first part built: 3 000 extremals of up to 6 s."""
    stream = FunnelStream.of_query(query)
    GoalFunnel.build(system, GOAL, problem.goal_offset, stream.draws(), n_simulations=3000,
                     time_weight=1.0, dt=DT, max_duration=DURATION, max_cost=500.0,
                     scale=system.metric_scale, tolerance=TOLERANCE)
    return stream


def _backwards(system, params: np.ndarray) -> np.ndarray:
    """The extremal with steering parameters ``params`` at the goal, integrated backwards
    for DURATION by the suite's RK4 of the textbook acrobot: its states (steps + 1, 4)."""
    lam, valid = system.costate_from_params(GOAL[None], params[None], 1.0)
    assert valid[0]
    rhs = references.state_costate_rhs(references.acrobot, 1, 1.0)
    return rk4(rhs, np.r_[GOAL, lam[0], 0.0], -DT, round(DURATION / DT))[:, :4]


def _dear_plan(system, problem, stream: FunnelStream | None):
    """A planner stand-in whose last query's funnel is ``stream`` (what `start_funnel` asks
    of a planner) and a solved plan whose path is one held-input edge costing 10^6."""
    settings = PlannerSettings(dt=DT, funnel_duration=DURATION, funnel_max_cost=500.0)
    planner = types.SimpleNamespace(problem=problem, propagator=Propagator(problem, settings),
                                    settings=settings, query_funnel=lambda: stream,
                                    funnel_reach=(DURATION, 500.0))
    tree = PlannerData(START, system.n_params, n_inputs=system.n_inputs)
    dear = Edge(np.vstack([START, START + 0.01]), 1, 1e6, 0.0, True, control=np.zeros(1))
    node = add_edge(tree, 0, dear, DT)
    return planner, Plan(system="acrobot", start=START, goal=GOAL, goal_tolerance=TOLERANCE,
                         time_weight=1.0, dt=DT, status="exact", planning_time_s=0.0,
                         planning_cpu_s=0.0, iterations=1, tree=tree, path_nodes=[0, node])


def test_the_search_comes_nearer_the_start_and_its_extremals_pass_where_it_says(acrobot):
    """Each round's pool is at least as near the start as the last; after the rounds its
    nearest extremal passes far nearer than any of the funnel's own. That extremal,
    integrated backwards from the goal here, passes the start at the distance the search
    records. A second stream of the same query gives the same pool bit for bit."""
    system, problem = acrobot
    stream = _stream(system, problem)
    search = stream.aimed(START, system, problem.offset_to)
    assert stream.aimed(START + 0.1, system, problem.offset_to) is None  # another start
    first = search.nearest
    nearest = [first]
    while search.step(stream.build) is not None:
        nearest.append(search.nearest)
    assert len(nearest) == AIM_ROUNDS + 1
    assert all(b <= a for a, b in pairwise(nearest))
    assert nearest[-1] < first / 5  # measured: 0.90 -> 0.036
    states = _backwards(system, search.pool[0][1])
    d = problem.offset_to(states, START) * system.metric_scale
    # the funnel keeps a state only while the extremal stays in the box and outside the
    # goal region: the nearest state here may only be nearer
    assert np.sqrt(np.einsum("ij,ij->i", d, d)).min() == pytest.approx(search.nearest,
                                                                        abs=1e-4)
    again = _stream(system, problem)
    other = again.aimed(START, system, problem.offset_to)
    while other.step(again.build) is not None:
        pass
    for (da, pa, ca), (db, pb, cb) in zip(search.pool, other.pool, strict=True):
        assert da == db and ca == cb
        np.testing.assert_array_equal(pa, pb)


def test_a_path_from_the_start_replaces_a_dearer_one_and_resimulates(acrobot):
    """`start_funnel` on a plan whose path (one stand-in edge) costs 10^6: the search's
    extremal through the start is steered along (the connection's continuation, else its
    multiple shooting along the extremal itself), and the chain becomes the path, below
    the root. Each edge, re-simulated here from its recorded start and costate, ends where
    the next begins and costs what it records; the last ends in the goal region."""
    system, problem = acrobot
    stream = _stream(system, problem)
    planner, plan = _dear_plan(system, problem, stream)
    tree, node = plan.tree, plan.path_nodes[1]
    out = improve.start_funnel(planner, plan)
    record = out.extra["start_funnel"]
    assert record["kept"] and record["rounds"] == AIM_ROUNDS and record["tries"] >= 1
    path = out.path_nodes
    assert path[0] == 0 and path[1:] == list(range(node + 1, tree.n_nodes))
    assert all(tree.kind(i) == "funnel" for i in path[1:])
    rhs = references.state_costate_rhs(references.acrobot, 1, 1.0)
    at = START
    for i in path[1:]:
        np.testing.assert_array_equal(tree.states[tree.parents[i]], at)
        end = rk4(rhs, np.r_[at, tree.costates[i], 0.0], DT,
                  round(tree.durations[i] / DT))[-1]
        np.testing.assert_allclose(end[:4], tree.states[i], atol=1e-4)
        assert end[-1] == pytest.approx(tree.costs[i], rel=1e-6)
        at = tree.states[i]
    assert np.linalg.norm(problem.goal_offset(at[None])) <= TOLERANCE
    assert out.path_cost < 100.0  # measured: 35.8


def test_without_a_funnel_the_plan_is_unchanged(acrobot):
    """No funnel built for the query (or no query solved): nothing to aim, the same plan."""
    system, problem = acrobot
    planner, plan = _dear_plan(system, problem, None)
    node = plan.path_nodes[1]
    out = improve.start_funnel(planner, plan)
    assert out.path_nodes == [0, node]
    assert out.extra["start_funnel"] == {"rounds": 0, "nearest": None, "tries": 0,
                                         "kept": False}


def test_the_grid_chain_steers_where_the_free_time_chain_stalls(acrobot):
    """Along the search's nearest extremal of query 2 (0.028 from the start) the funnel
    connection's continuation fails and multiple shooting with a free final time does too
    (segment ends between RK4 steps: the residual stalls); the same extremal cut on the RK4
    grid with its duration fixed (`FunnelConnection._grid_chain`) gives a chain from the
    start, each edge re-simulated here from its start and costate to its recorded end and
    cost, the last in the goal region (measured: cost 35.8)."""
    from rrtcolearn.planning.connections import FunnelConnection

    system, problem = acrobot
    stream = _stream(system, problem, query=2)
    search = stream.aimed(START, system, problem.offset_to)
    funnel = None
    while (part := search.step(stream.build)) is not None:
        funnel = part
    dist = search.distances(funnel)
    j = int(np.argmin(dist))
    assert dist[j] < 0.05
    settings = PlannerSettings(dt=DT, funnel_duration=DURATION, funnel_max_cost=500.0)
    conn = FunnelConnection(Propagator(problem, settings), funnel, duration=DURATION)
    offset = problem.goal_offset(START[None])[0]
    assert conn.steer(offset, j, 1.5 * DURATION) is None
    guess = funnel.extremal(j)
    grid = conn._grid_chain
    conn._grid_chain = lambda x0, g: None  # the chain as it was: free final time only
    assert conn._chain(START, guess, 1.5 * DURATION) is None
    conn._grid_chain = grid
    chain = conn._chain(START, guess, 1.5 * DURATION)
    assert chain is not None
    rhs = references.state_costate_rhs(references.acrobot, 1, 1.0)
    at = START
    for edge in chain:
        np.testing.assert_allclose(edge.traj[0, :4], at, atol=1e-12)
        end = rk4(rhs, np.r_[at, edge.costate, 0.0], DT, edge.steps)[-1]
        np.testing.assert_allclose(end[:4], edge.traj[-1, :4], atol=1e-4)
        assert end[-1] == pytest.approx(edge.cost, rel=1e-6)
        at = edge.traj[-1, :4]
    assert np.linalg.norm(problem.goal_offset(at[None])) <= TOLERANCE
    assert sum(e.cost for e in chain) < 100.0


def test_the_funnel_connection_steers_from_the_start_where_no_node_does(acrobot):
    """In a solve, where no tree node steers into the funnel, each call of the funnel
    connection runs a round of the query's aimed search and steers from the root along the
    pool's nearest extremal (`FunnelConnection._from_start`): on the suite's funnel it
    connects the start itself within the search's rounds, the chain re-simulating by the
    suite's RK4 into the goal region; the rounds stop at AIM_ROUNDS and are the query's
    (the anytime search continues them)."""
    from rrtcolearn.planning.connections import FunnelConnection

    system, problem = acrobot
    stream = _stream(system, problem)
    settings = PlannerSettings(dt=DT, funnel_duration=DURATION, funnel_max_cost=500.0)
    conn = FunnelConnection(Propagator(problem, settings), stream.parts[(0, 3000)],
                            duration=DURATION)
    tree = types.SimpleNamespace(data=types.SimpleNamespace(states=START[None]))
    assert conn._from_start(tree) is None  # no search without `aim`
    conn.aim(stream)
    found, calls = None, 0
    while found is None and calls <= AIM_ROUNDS:
        found, calls = conn._from_start(tree), calls + 1
    assert found is not None and found[0] == 0 and conn.aimed[1] >= 1
    assert conn.report()["funnel_aimed"] == conn.aimed
    rhs = references.state_costate_rhs(references.acrobot, 1, 1.0)
    at = START
    for edge in found[1]:
        end = rk4(rhs, np.r_[at, edge.costate, 0.0], DT, edge.steps)[-1]
        np.testing.assert_allclose(end[:4], edge.traj[-1, :4], atol=1e-4)
        assert end[-1] == pytest.approx(edge.cost, rel=1e-6)
        at = edge.traj[-1, :4]
    assert np.linalg.norm(problem.goal_offset(at[None])) <= TOLERANCE
    search = stream.aimed(START, system, problem.offset_to)
    assert search.rounds == conn.aimed[0]  # the query's search, shared
    for _ in range(AIM_ROUNDS - search.rounds):
        conn._from_start(tree)
    assert conn._from_start(tree) is None and search.rounds == AIM_ROUNDS
