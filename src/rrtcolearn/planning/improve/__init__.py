"""Improve a solved plan in its own tree, one job per module: goal shortcuts by shooting
(choose-parent for the goal, `goal`), interior shortcuts (a stretch of the path replaced by
one extremal, the rest re-attached; also between stations along the edges, `interior`),
landed shortcuts (the same with the stretch's duration kept, `landed`) and goal-funnel
extremals through the start (`start`). `shortcut` runs them; it is the anytime scheme's
``improve``. Indirect multiple shooting of the whole path (`multiple`) is here too; the
anytime scheme runs it before `shortcut` on each new best path, on an allowance of its own
(`anytime.solve_with_restarts`' ``first``; docs/anytime.md). What they share is in
`common`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from rrtcolearn.planning.improve.goal import goal_shortcuts
from rrtcolearn.planning.improve.interior import interior_shortcuts, piece_shortcuts
from rrtcolearn.planning.improve.landed import landed_shortcuts
from rrtcolearn.planning.improve.multiple import multiple_shooting
from rrtcolearn.planning.improve.start import start_funnel
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

__all__ = ["goal_shortcuts", "interior_shortcuts", "landed_shortcuts", "multiple_shooting",
           "piece_shortcuts", "shortcut", "start_funnel"]


def shortcut(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None,
             accept: Callable[[Plan], bool] | None = None) -> Plan:
    """``plan`` improved in its own tree: its tail replaced by an extremal or an LQR chain
    into the goal region (`goal_shortcuts`), then stretches of what is left by single
    extremals (`interior_shortcuts`), then stretches by single extremals over the same
    duration (`landed_shortcuts`), then the whole path by the goal funnel's extremal
    through the start where one undercuts it (`start_funnel`: run first it cost the
    acrobot's shortcuts their gains, median 4.63x -> 5.11x on seeds 0-7), then stretches
    between stations along the edges (`piece_shortcuts`, last: it takes what the others
    leave of the allowance; acrobot after 10 s, median 4.50x -> 3.21x); ``stop`` as all five
    take it. The anytime scheme's ``improve`` (``plan.anytime``). ``accept`` (the anytime
    scheme's, `evaluate.is_resolved`): the pieces' path is kept only where it accepts it,
    else the path before them (``extra["pieces"]["not_accepted"]``): a path it turns down
    is dropped whole, with the other shortcuts' gains (acrobot seed 7: 1.54x -> 3.07x).

    Not `multiple_shooting`: within this allowance it was cut on 341 of 343 tries (run
    last) or took the allowance the goal and interior shortcuts pay with (run first); the
    anytime scheme gives it one of its own (``first``; docs/anytime.md).

    Goal shortcuts first: where one extremal reaches the goal from early on (the pendulum)
    nothing is left for the interior to do, and under the anytime scheme's allowance the
    interior search run first left the goal walk too little CPU (the pendulum at u_max = 1,
    10 s: 5.785 against 5.668 on seed 0, 121 solves against 160)."""
    plan = landed_shortcuts(planner, interior_shortcuts(planner, goal_shortcuts(planner, plan,
                                                                                 stop), stop),
                            stop)
    plan = start_funnel(planner, plan, stop)
    cut = piece_shortcuts(planner, plan, stop)
    if cut is plan or accept is None or accept(cut):
        return cut
    plan.extra["pieces"] = {**cut.extra["pieces"], "not_accepted": True}
    return plan
