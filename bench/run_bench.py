"""`make bench`: offline and online figures of the pendulum swing-up, against the targets.

Prints a table and, as its last line, one JSON object. CPU figures are process (offline) or
thread (per plan) CPU time, medians over repeats, measured after a warm-up that compiles and
loads the numba kernels.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import numpy as np

from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import FittedModel, fit_functions, plan
from rrtcolearn.systems import make

REPEATS = 3
QUERIES = 100


def offline(system, cfg: Config, seed: int):
    t0 = time.process_time()
    data, _ = generate_data(system, seed, cfg.generate.n_simulations)
    t1 = time.process_time()
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max, seed=seed)
    t2 = time.process_time()
    functions = fit_functions(system, cleaned, cfg)
    t3 = time.process_time()
    return data, cleaned, functions, (t1 - t0, t2 - t1, t3 - t2)


def main() -> None:
    system = make("pendulum")
    cfg = Config()
    small, _ = generate_data(system, 0, 500)  # warm-up: load compiled kernels
    clean_data(small)
    times = []
    for r in range(REPEATS):
        data, cleaned, functions, t = offline(system, cfg, seed=1 + r)
        times.append(t)
        print(f"offline repeat {r}: generate {t[0]:.2f} s, clean {t[1]:.2f} s, "
              f"fit {t[2]:.2f} s CPU", file=sys.stderr)
    gen, cln, fit = (statistics.median(x) for x in zip(*times, strict=True))
    model = FittedModel(system, cfg, functions, float(cleaned.duration.max()),
                        cfg.generate.max_state_distance)
    plan(model, [-np.pi, 0], [0, 0], 0.1, seed=10_000)  # warm-up
    plans = [plan(model, [-np.pi, 0], [0, 0], 0.1, seed=s, time_limit=10.0)
             for s in range(QUERIES)]
    solved = [p for p in plans if p.solved]
    held, _ = generate_data(system, 123_456, 2000)
    err = held_out_errors(system, functions, held, n_queries=1000)

    def med(values):
        return float(np.median(values)) if len(values) else float("nan")

    result = {
        "offline_cpu_s": round(gen + cln + fit, 3),
        "generate_cpu_s": round(gen, 3),
        "clean_cpu_s": round(cln, 3),
        "fit_cpu_s": round(fit, 3),
        "raw_points": len(data),
        "kept_points": len(cleaned),
        "plan_success_rate": len(solved) / len(plans),
        "plan_cpu_s_median": round(med([p.planning_cpu_s for p in plans]), 5),
        "plan_cpu_s_p90": round(float(np.quantile([p.planning_cpu_s for p in plans], 0.9)), 5),
        "plan_nodes_median": med([p.nodes for p in plans]),
        "plan_iterations_median": med([p.iterations for p in plans]),
        "plan_cost_median": round(med([p.path_cost for p in solved]), 4),
        "steer_mse_median": float(f"{np.median(err.steer_mse):.3g}"),
        "cost_rel_error_median": float(f"{np.median(err.cost_rel_error):.3g}"),
        "held_out_accepted_fraction": round(err.accepted_fraction, 4),
    }
    targets = {
        "offline_cpu_s": ("<=", 10.0, "paper: ~25 min"),
        "plan_cpu_s_median": ("<=", 0.020, "paper: 2.36 s"),
        "plan_nodes_median": ("<=", 84, "paper: 84"),
        "steer_mse_median": ("<=", 0.11, "paper: 0.11"),
        "plan_success_rate": (">=", 1.0, "within 10 s"),
    }
    print(f"{'figure':28s} {'value':>12s}  target")
    for key, value in result.items():
        line = f"{key:28s} {value!s:>12s}"
        if key in targets:
            op, bound, note = targets[key]
            ok = value <= bound if op == "<=" else value >= bound
            line += f"  {op} {bound} ({note}) {'met' if ok else 'NOT met'}"
        print(line)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
