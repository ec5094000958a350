"""Random controls widen within a solve (`controls.RandomControls.widen`): the draws start in
the narrowest box (where the dearest input costs as much as the time) and the box doubles
after WIDEN_AFTER iterations in a row with no node nearer the goal, up to the solve's scale."""

from __future__ import annotations

from itertools import pairwise

import numpy as np

from rrtcolearn.planning.controls import WIDEN_AFTER
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.settings import PlannerSettings
from rrtcolearn.planning.termination import TerminationCondition

START, GOAL = [-np.pi, 0.0], [0.0, 0.0]


def _planner(pendulum, tolerance: float, u_max: float = 4.0) -> RRTCoLearn:
    problem = PlanningProblem.create(pendulum, START, GOAL, tolerance, u_max=u_max)
    return RRTCoLearn(problem, None, PlannerSettings(time_weight=1.0))


def _recorded(planner: RRTCoLearn) -> list[tuple[int, int, float]]:
    """(iterations, nodes, scale) after every widening check of ``planner``'s solves."""
    log: list[tuple[int, int, float]] = []
    widen = planner.controls.widen

    def logged(rng, tree, progress):
        widen(rng, tree, progress)
        log.append((progress.iterations, tree.data.n_nodes, planner.controls.scale))
    planner.controls.widen = logged
    return log


def test_draws_start_narrow_and_widen_to_the_whole_box(pendulum):
    """A goal too small to reach: the first edges hold inputs of the narrowest box
    (|u| <= sqrt(2 w)), the scale only doubles, and it reaches the whole box."""
    planner = _planner(pendulum, 1e-9)
    narrowest = planner.controls.narrowest_scale()
    log = _recorded(planner)
    p = planner.solve(TerminationCondition(None, 20 * WIDEN_AFTER), 0)
    scales = [s for _, _, s in log]
    assert scales[0] == narrowest and scales[-1] == 1.0 and not p.solved
    assert all(b in (a, min(1.0, 2 * a)) for a, b in pairwise(scales))
    first_wide = next(i for i, (_, _, s) in enumerate(log) if s > narrowest)
    nodes = log[first_wide - 1][1]  # nodes added in the narrowest box
    assert nodes > 10
    d = p.tree
    narrow = [abs(float(d.controls[i][0])) for i in range(1, nodes) if d.kind(i) == "control"]
    assert narrow and max(narrow) <= np.sqrt(2.0) + 1e-12
    wide = [abs(float(d.controls[i][0])) for i in range(1, d.n_nodes) if d.kind(i) == "control"]
    assert max(wide) > 2.0  # the wider boxes were drawn from


def test_a_box_that_costs_no_more_than_time_is_never_narrowed(pendulum):
    """|u| <= 1 costs at most w: the draws come from the whole box throughout."""
    planner = _planner(pendulum, 1e-9, u_max=1.0)
    log = _recorded(planner)
    planner.solve(TerminationCondition(None, 2000), 0)
    assert {s for _, _, s in log} == {1.0}


def test_widening_is_the_same_compiled_and_in_python(pendulum):
    """The compiled batches end where a widening is due, so the tree is the Python loop's
    (a goal reached at the narrowest scale, and one never reached: the box widens)."""
    compiled, python = _planner(pendulum, 0.1), _planner(pendulum, 0.1)
    never = (_planner(pendulum, 1e-9), _planner(pendulum, 1e-9))
    never[1].controls.batch_constants = lambda tree: None
    python.controls.batch_constants = lambda tree: None  # every iteration in Python
    log = _recorded(never[0])
    for seed, (one, other) in zip((0, 1, 0, 1), ((compiled, python), (compiled, python),
                                                  never, never), strict=True):
        a = one.solve(TerminationCondition(None, 4000), seed)
        b = other.solve(TerminationCondition(None, 4000), seed)
        assert a.iterations == b.iterations and a.tree.n_nodes == b.tree.n_nodes
        n = a.tree.n_nodes
        for name in ("states", "parents", "controls", "costs"):
            np.testing.assert_array_equal(getattr(a.tree, name)[:n], getattr(b.tree, name)[:n])
    assert len({s for _, _, s in log}) > 1  # some solve widened
