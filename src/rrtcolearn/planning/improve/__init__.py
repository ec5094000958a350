"""Improve a solved plan in its own tree, one job per module: goal shortcuts by shooting
(choose-parent for the goal, `goal`), interior shortcuts (a stretch of the path replaced by
one extremal, the rest re-attached, `interior`), landed shortcuts (the same with the
stretch's duration kept, `landed`) and goal-funnel extremals through the start (`start`).
`shortcut` runs them in that order; it is the anytime scheme's ``improve``. Indirect
multiple shooting of the whole path (`multiple`) is here too; the anytime scheme runs it
before `shortcut` on each new best path, on an allowance of its own
(`anytime.solve_with_restarts`' ``first``; docs/anytime.md). What they share is in
`common`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from rrtcolearn.planning.improve.goal import goal_shortcuts
from rrtcolearn.planning.improve.interior import interior_shortcuts
from rrtcolearn.planning.improve.landed import landed_shortcuts
from rrtcolearn.planning.improve.multiple import multiple_shooting
from rrtcolearn.planning.improve.start import start_funnel
from rrtcolearn.planning.tree import Plan

if TYPE_CHECKING:
    from rrtcolearn.planning.rrt import RRTCoLearn

__all__ = ["goal_shortcuts", "interior_shortcuts", "landed_shortcuts", "multiple_shooting",
           "shortcut", "start_funnel"]


def shortcut(planner: RRTCoLearn, plan: Plan, stop: Callable[[], bool] | None = None
             ) -> Plan:
    """``plan`` improved in its own tree: its tail replaced by an extremal or an LQR chain
    into the goal region (`goal_shortcuts`), then stretches of what is left by single
    extremals (`interior_shortcuts`), then stretches by single extremals over the same
    duration (`landed_shortcuts`), then the whole path by the goal funnel's extremal
    through the start where one undercuts it (`start_funnel`, last: it takes what the
    others leave of the allowance; run first it cost the acrobot's shortcuts their gains,
    median 4.63x -> 5.11x on seeds 0-7); ``stop`` as all four take it. The anytime scheme's
    ``improve`` (``plan.anytime``).

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
    return start_funnel(planner, plan, stop)
