"""A/B of plan.input_limit ("reject" against "cut") at u_max = 1 (w = 0.1) and u_max = 2.

Usage: python bench/input_limit_ab.py (about a minute). Both settings run on the same model
and seeds, twice, alternating, so machine load affects both alike.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rrtcolearn.config import load_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions
from rrtcolearn.planning import PlanningProblem, RRTCoLearn, TerminationCondition
from rrtcolearn.systems import make


def main() -> None:
    system = make("pendulum")
    for u_max, w in [(1.0, 0.1), (2.0, 1.0)]:
        cfg = load_config(overrides=[f"system.u_max={u_max}", f"system.time_weight={w}"])
        data, _ = generate_data(system, 1, 40000, u_max=u_max, time_weight=w)
        cleaned, _ = clean_data(data, seed=1)
        model = FittedModel(system, cfg, fit_functions(system, cleaned, cfg),
                            float(cleaned.duration.max()), 1.5)
        problem = PlanningProblem.create(system, [-np.pi, 0], [0, 0], 0.1, u_max=u_max)
        for mode in ("reject", "cut", "reject", "cut"):
            settings = dataclasses.replace(model.planner_settings(), input_limit=mode)
            plans = [RRTCoLearn(problem, model.functions, settings)
                     .solve(TerminationCondition(10.0), seed) for seed in range(60)]
            solved = [p for p in plans if p.solved]
            print(f"u_max={u_max:g} {mode:6s} success {len(solved) / len(plans):.2f} "
                  f"cpu {1e3 * np.median([p.planning_cpu_s for p in plans]):.1f} ms "
                  f"nodes {np.median([p.nodes for p in plans]):.1f} "
                  f"cost {np.median([p.path_cost for p in solved]):.2f}")


if __name__ == "__main__":
    main()
