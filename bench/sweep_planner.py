"""Measure the planner defaults the paper leaves open: validity threshold and goal bias.

Usage: python bench/sweep_planner.py  (about 2 minutes). Prints one row per setting over
100 seeded swing-up queries (tolerance 0.1) on one 40000-simulation epoch (seed 1).
"""

from __future__ import annotations

import numpy as np

from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import FittedModel, fit_functions, plan
from rrtcolearn.systems import make


def main() -> None:
    system = make("pendulum")
    data, _ = generate_data(system, 1, 40000)
    cleaned, _ = clean_data(data, seed=1)
    held, _ = generate_data(system, 99, 2000)
    print(f"{'threshold':>9s} {'goal_bias':>9s} {'accepted':>8s} {'success':>7s} "
          f"{'cpu_ms':>7s} {'nodes':>6s} {'iters':>6s} {'cost':>6s}")
    for thr, bias in [(0.3, 0.2), (0.4, 0.2), (0.5, 0.2), (0.6, 0.2), (0.8, 0.2),
                      (0.5, 0.05), (0.5, 0.1), (0.5, 0.3)]:
        cfg = Config()
        cfg = cfg.model_copy(update={
            "learn": cfg.learn.model_copy(update={"validity_threshold": thr}),
            "plan": cfg.plan.model_copy(update={"goal_bias": bias})})
        functions = fit_functions(system, cleaned, cfg)
        model = FittedModel(system, cfg, functions, float(cleaned.duration.max()), 1.5)
        plan(model, [-np.pi, 0], [0, 0], 0.1, seed=999)
        plans = [plan(model, [-np.pi, 0], [0, 0], 0.1, seed=s) for s in range(100)]
        acc = held_out_errors(system, functions, held, n_queries=10).accepted_fraction
        ok = [p for p in plans if p.solved]
        print(f"{thr:9.2f} {bias:9.2f} {acc:8.3f} {len(ok) / len(plans):7.2f} "
              f"{1e3 * np.median([p.planning_cpu_s for p in plans]):7.1f} "
              f"{np.median([p.nodes for p in plans]):6.1f} "
              f"{np.median([p.iterations for p in plans]):6.1f} "
              f"{np.median([p.path_cost for p in ok]):6.2f}")


if __name__ == "__main__":
    main()
