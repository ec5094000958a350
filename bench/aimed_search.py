"""CPU of the aimed search for goal-funnel extremals through the start (`funnel.AimedSearch`).

On the textbook acrobot's swing-up (hanging to upright, goal radius 0.3): for each query
seed, the query's funnel stream with its first part (3 000 extremals of up to 6 s, as in
tests/test_start_funnel.py) built, then the search's rounds until it stops; prints the
rounds' process CPU and the nearest distance reached per query, and their median. No model
is needed. ``PYTHONPATH=<checkout>/src python bench/aimed_search.py`` measures another
checkout: run two alternately for a ratio on a shared machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from rrtcolearn.planning.funnel import FunnelStream, GoalFunnel
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.systems import make

GOAL = np.array([np.pi, 0.0, 0.0, 0.0])
START = np.zeros(4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, nargs="+", default=[1, 3], help="query seeds")
    args = ap.parse_args()
    system = make("acrobot")
    problem = PlanningProblem.create(system, START, GOAL, 0.3, wrap_goal=True)
    cpu = []
    for q in args.queries:
        stream = FunnelStream.of_query(q)
        GoalFunnel.build(system, GOAL, problem.goal_offset, stream.draws(),
                         n_simulations=3000, time_weight=1.0, dt=0.01, max_duration=6.0,
                         max_cost=500.0, scale=system.metric_scale, tolerance=0.3)
        search = stream.aimed(START, system, problem.offset_to)
        t = time.process_time()
        while search.step(stream.build) is not None:
            pass
        cpu.append(time.process_time() - t)
        print(f"query {q}: {search.rounds} rounds, {cpu[-1]:.3f} s CPU, "
              f"nearest {search.nearest:.6g}")
    print(f"median {statistics.median(cpu):.3f} s CPU")


if __name__ == "__main__":
    main()
