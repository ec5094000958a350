"""Indirect multiple shooting of the best path (`planning.improve.multiple_shooting`,
`planning.shooting.multiple_shoot`): the whole path relaxed into one extremal from the start
into the goal, built as a chain of extremal edges below the root. Checked against a plain
RK4 of the pendulum's own state+costate equations written in tests/conftest.py (no code
shared with the planner): the chain joins, ends in the goal ball at the cost it records,
its costate is continuous where its edges meet, and H* = 0 holds up to the rounding of the
segments' durations to the RK4 grid."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import rk4_numpy
from tests.swingup import (
    GOAL,
    START,
    assert_grown_by_leaves,
    first_solution,
    swingup_planner,
    tree_snapshot,
)

from rrtcolearn.evaluate import check_plan
from rrtcolearn.planning.improve import multiple_shooting

# first paths of the paper's pendulum model that multiple shooting turns into one extremal
# (seed 0 unbounded: 4 segments; seed 2 at u_max = 2 by truncation: 3 segments)
CASES = [(None, 0), (2.0, 2)]


@pytest.mark.parametrize(("u_max", "seed"), CASES)
def test_one_extremal_resimulated_independently(paper_model, u_max, seed):
    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, seed)
    first = p.path_cost
    q = multiple_shooting(planner, p)
    rec = q.extra["multiple_shooting"]
    assert rec["kept"] and rec["converged"] and rec["segments"] >= 2
    assert q.path_cost < first
    w, dt = q.time_weight, q.dt
    x, cost, ends = START, 0.0, []
    edges = q.edges()
    assert len(edges) >= 2
    for e in edges:
        assert e["control"] is None  # every edge an extremal
        assert np.abs(np.asarray(e["from"]) - x).max() < 1e-12
        steps = round(e["duration"] / dt)
        # the paper's Eqs. 6-7 (u = -lambda_omega) and the running cost, plain RK4
        traj = rk4_numpy(np.r_[e["from"], e["costate"], 0.0], w, dt, steps)
        assert np.abs(traj[-1, :2] - e["to"]).max() < 1e-9
        assert traj[-1, 4] == pytest.approx(e["cost"], rel=1e-9, abs=1e-12)
        if u_max is not None:
            assert np.abs(traj[:, 3]).max() <= u_max + 1e-9
        ends.append(traj[-1, 2:4])
        x, cost = traj[-1, :2], cost + traj[-1, 4]
    assert cost == pytest.approx(q.path_cost, rel=1e-9)
    assert np.linalg.norm(x - GOAL) <= 0.1
    # costate continuity where the edges meet: one extremal, up to the solve's tolerance
    for end, e in zip(ends[:-1], edges[1:], strict=True):
        lam = np.asarray(e["costate"])
        assert np.abs(end - lam).max() <= 1e-6 * max(1.0, np.abs(lam).max())
    # free final time: H* = w + lambda . f - lambda_omega^2 / 2 = 0 at the start, up to
    # the durations' rounding to the grid (half a step of a few seconds' extremal)
    lam = np.asarray(edges[0]["costate"])
    h = w + lam[0] * START[1] + lam[1] * np.sin(START[0]) - 0.5 * lam[1] ** 2
    assert abs(h) < 0.05 * w
    r = check_plan(paper_model.system, q, goal_fn=planner.problem.goal_distance)
    assert r["path_cost"] == pytest.approx(q.path_cost, rel=1e-9)


@pytest.mark.parametrize(("u_max", "seed"), CASES)
def test_only_leaves_are_added_and_every_edge_resimulates(paper_model, u_max, seed):
    planner = swingup_planner(paper_model, u_max)
    p = first_solution(planner, seed)
    before = tree_snapshot(p.tree)
    q = multiple_shooting(planner, p)
    # the chain hangs below the root: one new node per edge of the path
    assert q.path_nodes[0] == 0
    assert_grown_by_leaves(before, q, len(q.path_nodes) - 1, paper_model.system)
    assert set(q.duration_by) == {"shooting"}


@pytest.mark.parametrize(("u_max", "seed"), CASES)
def test_deterministic(paper_model, u_max, seed):
    """The same plan gives the same extremal, bit for bit."""
    planner = swingup_planner(paper_model, u_max)
    a = multiple_shooting(planner, first_solution(planner, seed))
    b = multiple_shooting(planner, first_solution(planner, seed))
    assert a.extra["multiple_shooting"]["kept"]
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.extra["multiple_shooting"] == b.extra["multiple_shooting"]


def test_stop_and_never_dearer(paper_model):
    """``stop()`` true at once: the plan as it was; run again on its own result, never
    dearer."""
    planner = swingup_planner(paper_model)
    p = first_solution(planner, 0)
    cost, nodes = p.path_cost, p.tree.n_nodes
    q = multiple_shooting(planner, p, stop=lambda: True)
    assert q.path_cost == cost and q.tree.n_nodes == nodes
    assert q.extra["multiple_shooting"]["why"] == "stopped"
    once = multiple_shooting(planner, first_solution(planner, 0))
    cost = once.path_cost
    assert multiple_shooting(planner, once).path_cost <= cost


def test_segments_follow_the_path():
    """Path nodes merged greedily into segments of at most the longest duration; an edge
    longer than that is a segment of its own."""
    from rrtcolearn.planning.improve.multiple import _segments

    assert _segments(np.array([1.0, 1.0, 1.0, 1.0]), 2.0) == [0, 2]
    assert _segments(np.array([0.5, 3.0, 0.5, 0.5]), 1.0) == [0, 1, 2]
    assert _segments(np.array([0.4, 0.4, 0.4]), 5.0) == [0]
