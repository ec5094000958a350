"""The restart anytime baseline (`rrtcolearn.anytime`): the whole budget spent on solves with
fresh seeds, the cheapest path kept, its progress recorded."""

from __future__ import annotations

import time
from functools import partial
from itertools import pairwise

import numpy as np
import pytest
from tests.swingup import GOAL, START, plan_swingup

from rrtcolearn import planners
from rrtcolearn.anytime import ALLOWANCE, solve_with_restarts
from rrtcolearn.config import PlanConfig
from rrtcolearn.evaluate import resimulate
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.termination import TerminationCondition

LIMIT = 1.0  # a time budget (the tests of it assert durations, with a wide margin above)
MARGIN = 60.0


def _random_rrt(pendulum):
    """The random-control RRT peer's ``solve(termination, seed)`` on the swing-up within
    0.3 of the goal, |u| <= 2: a planner for the restart baseline without a model."""
    problem = PlanningProblem.create(pendulum, START, GOAL, 0.3, u_max=2.0)
    return partial(planners.make("random-rrt", time_weight=1.0).solve, problem)


def test_off_by_default():
    assert PlanConfig().anytime is False


def test_keeps_the_first_solution_and_never_gets_worse(paper_model):
    first = plan_swingup(paper_model, 3, max_iterations=2000)
    p = plan_swingup(paper_model, 3, anytime=True, max_iterations=2000)
    a = p.extra["anytime"]
    assert first.solved and p.solved and a["solves"] > 1
    costs = [c for _, c in a["progress"]]
    cpus = [t for t, _ in a["progress"]]
    assert costs[0] == pytest.approx(first.path_cost, rel=1e-12)  # the plain solve's
    assert all(b < c for c, b in pairwise(costs))  # only improvements
    assert all(b >= c for c, b in pairwise(cpus))
    assert p.path_cost == pytest.approx(costs[-1], rel=1e-12)
    assert p.path_cost <= first.path_cost
    r = resimulate(paper_model.system, p)  # the kept plan is what it claims
    assert r["max_gap"] < 1e-9 and r["max_cost_gap"] < 1e-9
    assert r["path_cost"] == pytest.approx(p.path_cost, rel=1e-9)


def test_an_iteration_budget_gives_the_same_plan_for_the_same_seed(paper_model):
    a, b = (plan_swingup(paper_model, 5, anytime=True, max_iterations=1500) for _ in range(2))
    assert a.to_dict()["path"] == b.to_dict()["path"]
    assert a.extra["anytime"]["solves"] == b.extra["anytime"]["solves"]
    assert [c for _, c in a.extra["anytime"]["progress"]] == \
        [c for _, c in b.extra["anytime"]["progress"]]


def test_any_planner_and_a_budget_is_required(pendulum):
    """The baseline wraps any planner's solve (here the random-control RRT's); without a
    limit it would never stop, so it refuses."""
    solve = _random_rrt(pendulum)
    p = solve_with_restarts(solve, TerminationCondition(None, 6000), seed=1)
    costs = [c for _, c in p.extra["anytime"]["progress"]]
    assert p.solved and costs and all(b < c for c, b in pairwise(costs))
    with pytest.raises(ValueError, match="budget"):
        solve_with_restarts(solve, TerminationCondition(None, None), seed=1)


def test_the_anytime_record_counts_every_iteration(paper_model):
    p = plan_swingup(paper_model, 0, anytime=True, max_iterations=1500)
    record = p.extra["anytime"]
    assert record["solves"] > 1 and p.iterations < record["iterations"] <= 1500


def test_the_anytime_scheme_spends_a_time_budget(paper_model):
    """With a time limit (no iteration limit) the restarts and shortcuts run until the limit;
    the first solution is the plain solve's (same seed), later ones only improve it."""
    first = plan_swingup(paper_model, 3, max_iterations=3000)
    wall = time.perf_counter()
    p = plan_swingup(paper_model, 3, anytime=True, time_limit=LIMIT)
    wall = time.perf_counter() - wall
    a = p.extra["anytime"]
    assert LIMIT <= wall < LIMIT + MARGIN
    # how many solves fit in a wall second depends on the machine's load (one, under load
    # 11, with the interior shortcuts); restarts are asserted under iteration budgets above
    assert p.solved and a["solves"] >= 1 and a["scheme"] == "restarts+shortcut"
    costs = [c for _, c in a["progress"]]
    assert costs[0] == pytest.approx(first.path_cost, rel=1e-12)
    assert all(b < c for c, b in pairwise(costs)) and p.path_cost == costs[-1]
    r = resimulate(paper_model.system, p)
    assert r["max_gap"] < 1e-9 and r["path_cost"] == pytest.approx(p.path_cost, rel=1e-9)


def test_the_restart_baseline_spends_a_cpu_budget(pendulum):
    solve = _random_rrt(pendulum)
    cpu = time.process_time()
    p = solve_with_restarts(solve, TerminationCondition(time_limit=None, cpu_time_limit=LIMIT),
                            seed=1)
    cpu = time.process_time() - cpu
    a = p.extra["anytime"]
    assert LIMIT <= cpu < LIMIT + MARGIN
    assert p.solved and a["scheme"] == "restarts" and a["solves"] > 1
    assert p.path_cost == min(c for _, c in a["progress"])


def _random_planner(pendulum, u_max=4.0):
    """Random controls and the LQR connection alone (no learned functions): every edge but
    the LQR chains' is a random control, drawn from the box the solve was given."""
    from rrtcolearn.planning.rrt import RRTCoLearn
    from rrtcolearn.planning.settings import PlannerSettings

    problem = PlanningProblem.create(pendulum, START, GOAL, 0.3, u_max=u_max)
    return RRTCoLearn(problem, None, PlannerSettings(time_weight=1.0))


def test_the_narrowest_box_costs_as_much_as_the_time(pendulum):
    """The narrowest box's dearest input costs w: u^2 R / 2 = w with the pendulum's R = 1,
    |u| = sqrt(2 w); a box already that cheap is not narrowed."""
    planner = _random_planner(pendulum, u_max=4.0)
    s = planner.controls.narrowest_scale()
    assert s == pytest.approx(np.sqrt(2.0) / 4.0, rel=1e-9)
    low, high = planner.controls.draw_box(s)
    assert low == pytest.approx([-np.sqrt(2.0)]) and high == pytest.approx([np.sqrt(2.0)])
    assert planner.controls.draw_box(1.0) is not None
    assert all(a is b for a, b in zip(planner.controls.draw_box(1.0),
                                      planner.propagator.control_box, strict=True))
    assert _random_planner(pendulum, u_max=1.0).controls.narrowest_scale() == 1.0


def test_later_solves_draw_from_the_narrowed_box(pendulum):
    """Every random-control edge of every solve lies in the box of that solve's scale; the
    scale halves only after a solve cheaper than every earlier one and doubles back after a
    narrowed solve that was not; the best cost only falls; an iteration budget gives the
    same plan and scales for the same seed."""
    planner = _random_planner(pendulum)
    narrowest = planner.controls.narrowest_scale()

    def run():
        plans: list = []

        def solve(termination, seed, scale=1.0):
            plans.append((scale, planner.solve(termination, seed, scale)))
            return plans[-1][1]

        p = solve_with_restarts(solve, TerminationCondition(None, 20000), seed=2,
                                narrowest=narrowest)
        return p, plans

    p, plans = run()
    scales = p.extra["anytime"]["control_scales"]
    assert [s for s, _ in plans] == scales and len(scales) > 3 and min(scales) < 1.0
    cheapest = np.inf
    for (scale, q), following in zip(plans, [*scales[1:], None], strict=True):
        d = q.tree
        low, high = 4.0 * scale * np.array([-1.0, 1.0])
        inputs = [float(d.controls[i][0]) for i in range(1, d.n_nodes) if d.kind(i) == "control"]
        assert inputs and low <= min(inputs) and max(inputs) <= high
        if following is not None:
            cheaper = q.solved and q.path_cost < cheapest
            expected = max(narrowest, scale / 2) if cheaper else min(1.0, 2 * scale) \
                if scale < 1.0 else scale
            assert following == pytest.approx(expected)
        if q.solved:
            cheapest = min(cheapest, q.path_cost)
    costs = [c for _, c in p.extra["anytime"]["progress"]]
    assert all(b < c for c, b in pairwise(costs)) and p.path_cost == costs[-1]
    assert costs[0] == plans[0][1].path_cost and plans[0][0] == 1.0  # the plain first solve
    again, _ = run()
    assert again.to_dict()["path"] == p.to_dict()["path"]
    assert again.extra["anytime"]["control_scales"] == scales


def _counting(log: list):
    """An improvement that asks ``stop()`` until it is told to stop and logs (the plan's
    cost, its solve's iterations, the calls); it never changes the plan."""
    def step(p, stop):
        calls = 1
        while not stop():
            calls += 1
        log.append((p.path_cost, p.iterations, calls))
        return p
    return step


def test_the_first_improvement_has_an_allowance_of_its_own(pendulum):
    """``first`` runs only on a path cheaper than every earlier one, each try within the
    iterations of all solves so far times (its gains + 1) / (its tries + 1), and
    ``improve``'s allowance follows ``improve``'s own record: both checked call by call
    against the formula."""
    peer_solve = _random_rrt(pendulum)
    solves: list = []

    def solve(termination, seed):
        p = peer_solve(termination, seed)
        solves.append((p.solved, p.path_cost, p.iterations))
        return p

    def run():
        solves.clear()
        first_log, improve_log = [], []
        p = solve_with_restarts(solve, TerminationCondition(None, 20000), seed=1,
                                improve=_counting(improve_log), first=_counting(first_log))
        return p, list(solves), first_log, improve_log

    p, solved, first_log, improve_log = run()
    # the paths cheaper than all earlier ones, in order
    news, grown, best = [], [], np.inf  # with the iterations of all solves up to them
    total = 0
    for ok, cost, its in solved:
        total += max(1, its)
        if ok and cost < best:
            news.append(cost)
            grown.append(total)
            best = cost
    assert len(news) >= 2 and [c for c, _, _ in first_log] == news
    assert p.extra["anytime"]["first"] == {"tries": len(news), "gains": 0}
    # a try stops at the first stop() call past its share (but the last, at the budget):
    # ``first``'s of all solves so far, ``improve``'s of its own solve
    for k, (_, _, calls) in enumerate(first_log[:-1]):
        assert calls == int(ALLOWANCE * grown[k] / (k + 1)) + 1
    assert len(improve_log) == sum(ok for ok, _, _ in solved) > len(news)
    for j, (_, its, calls) in enumerate(improve_log[:-1]):
        assert calls == int(ALLOWANCE * max(1, its) / (j + 1)) + 1
    # with an iteration budget the same seed gives the same calls and the same plan
    q, solved2, first_log2, improve_log2 = run()
    assert (solved2, first_log2, improve_log2) == (solved, first_log, improve_log)
    assert q.to_dict()["path"] == p.to_dict()["path"]


def test_accept_keeps_the_cheapest_accepted_plan(pendulum):
    """With ``accept`` the best is the cheapest solved plan it accepts, whatever cheaper
    plans it turned down; where it accepts none, the cheapest plan (as without it). Checked
    against the log of every solve (no improvement: the solves' own plans)."""
    peer_solve = _random_rrt(pendulum)
    costs: list[float] = []

    def solve(termination, seed):
        p = peer_solve(termination, seed)
        if p.solved:
            costs.append(p.path_cost)
        return p

    def run(accept):
        costs.clear()
        p = solve_with_restarts(solve, TerminationCondition(None, 20000), seed=2,
                                accept=accept)
        return p, list(costs)

    plain, logged = run(None)
    assert len(logged) >= 3 and plain.path_cost == min(logged)
    # turn down the cheapest half: the best is the cheapest of the dearer half
    cut = float(np.median(logged))
    p, logged2 = run(lambda q: q.path_cost >= cut)
    assert logged2 == logged  # the same solves: accept does not change them
    assert p.path_cost == min(c for c in logged if c >= cut) > min(logged)
    assert p.extra["anytime"]["not_accepted"] >= 1
    assert "not_accepted" not in plain.extra["anytime"]
    nothing, _ = run(lambda q: False)
    assert nothing.path_cost == min(logged)
    assert nothing.extra["anytime"]["not_accepted"] == len(logged)
