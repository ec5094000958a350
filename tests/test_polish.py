"""``plan.polish``: one improvement round on the first solution (`anytime.solve_with_restarts`
with ``solves=1``) before `pipeline.plan` returns; docs/anytime.md."""

from __future__ import annotations

import numpy as np
import pytest
from tests.swingup import plan_swingup, swingup_planner

from rrtcolearn.anytime import solve_with_restarts
from rrtcolearn.cli.planning import plan_summary
from rrtcolearn.config import PlanConfig
from rrtcolearn.evaluate import resimulate
from rrtcolearn.planning.termination import TerminationCondition

SEEDS = (0, 1, 2, 3)


def _plan(model, seed, polish=True, time_limit=None, iterations=3000):
    return plan_swingup(model, seed, polish=polish, time_limit=time_limit,
                        max_iterations=iterations)


def test_off_by_default():
    assert PlanConfig().polish is False


@pytest.mark.parametrize("seed", SEEDS)
def test_polished_path_is_the_first_or_cheaper_and_resimulates(paper_model, seed):
    """The raw first path is the plain plan's (same seed, same tree); the polished one never
    costs more, and re-simulated edge by edge it is what it claims."""
    raw = _plan(paper_model, seed, polish=False)
    p = _plan(paper_model, seed)
    record = p.extra["polish"]
    assert "anytime" not in p.extra and raw.solved and p.solved
    assert record["first_cost"] == pytest.approx(raw.path_cost, rel=1e-12)
    assert record["cost"] == p.path_cost <= record["first_cost"]
    assert p.iterations == raw.iterations and record["steps"] >= 1
    np.testing.assert_array_equal(p.tree.states[:raw.tree.n_nodes],
                                  raw.tree.states[:raw.tree.n_nodes])
    r = resimulate(paper_model.system, p)
    assert r["max_gap"] < 1e-9 and r["path_cost"] == pytest.approx(p.path_cost, rel=1e-9)


def test_an_iteration_budget_gives_the_same_polish_for_the_same_seed(paper_model):
    a, b = (_plan(paper_model, 5) for _ in range(2))
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.extra["polish"]["steps"] == b.extra["polish"]["steps"]


def test_a_time_limit_gives_the_same_polish_too(paper_model):
    """The allowance is in improvement steps under a time limit as well: a plan whose solve
    ends well within the limit is polished the same on any machine."""
    a = _plan(paper_model, 5)
    b = _plan(paper_model, 5, time_limit=60.0, iterations=None)
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.extra["polish"]["steps"] == b.extra["polish"]["steps"]


def test_the_summary_shows_both_costs(paper_model):
    s = plan_summary(_plan(paper_model, 1))
    assert s["first_solution_cost"] >= s["polished_cost"] == s["path_cost"]


def test_one_solve_needs_no_budget(paper_model):
    """``solves=1`` stops by itself: no budget is required (the plain plan needs none)."""
    planner = swingup_planner(paper_model)
    p = solve_with_restarts(planner.solve, TerminationCondition(None, None), 2, solves=1)
    assert p.extra["anytime"]["solves"] == 1 and p.solved
    with pytest.raises(ValueError, match="solves"):
        solve_with_restarts(planner.solve, TerminationCondition(None, 100), 2, solves=0)
