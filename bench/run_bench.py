"""`make bench`: offline and online figures of the pendulum swing-up, against the targets,
then the parallel-generation speed-up, the soak, per-system figures (`systems_bench.py
--quick`) and the torque-limit table (`limits_bench.py`: saturated against truncated
extremals and OMPL's RRT, 100 queries per row). The last two run in processes of their own
beside the pendulum figures (every figure is CPU time of its own process or thread, so the
sharing of the two cores moves wall times only).

Prints a table and, as its last line, one JSON object. CPU figures are process (offline) or
thread (per plan) CPU time, medians over repeats, measured after a warm-up that compiles and
loads the numba kernels.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import FittedModel, fit_functions, plan, resolve
from rrtcolearn.systems import make

REPEATS = 3
QUERIES = 100
LIMIT_QUERIES = 50
# a shortened soak keeps `make bench` within its 5 minutes on a slow machine (66 ms CPU per
# query there); `python bench/soak.py` runs the full 10 000
SOAK_QUERIES = 500
# a box across the direct swing (theta, omega): the plan must pass above or below it
BLOCKING_BOX = {"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]}


def plan_stats(models, prefix: str, n: int = QUERIES, **kwargs) -> dict:
    """Success, CPU, nodes and cost over n seeded swing-up queries (tolerance 0.1) on each
    model (a list of epochs' models, or one)."""
    models = models if isinstance(models, list) else [models]
    plans = []
    for model in models:
        plan(model, [-np.pi, 0], [0, 0], 0.1, seed=10_000, **kwargs)  # warm-up
        plans += [plan(model, [-np.pi, 0], [0, 0], 0.1, seed=s, time_limit=10.0, **kwargs)
                  for s in range(n)]
    solved = [p for p in plans if p.solved]
    cpu = [p.planning_cpu_s for p in plans]
    # with several models, also each one's median (the same plans, not planned again)
    per_model = {f"{prefix}plan_cpu_s_median_per_epoch": [
        round(float(np.median(cpu[i * n : (i + 1) * n])), 5) for i in range(len(models))]
    } if len(models) > 1 else {}
    return per_model | {
        f"{prefix}success_rate": len(solved) / len(plans),
        f"{prefix}plan_cpu_s_median": round(float(np.median(cpu)), 5),
        f"{prefix}plan_cpu_s_p90": round(float(np.quantile(cpu, 0.9)), 5),
        f"{prefix}plan_nodes_median": float(np.median([p.nodes for p in plans])),
        f"{prefix}plan_iterations_median": float(np.median([p.iterations for p in plans])),
        f"{prefix}plan_cost_median": round(float(np.median([p.path_cost for p in solved])), 4)
        if solved else None,
        f"{prefix}max_abs_u": round(max((p.max_abs_u for p in solved), default=0.0), 4),
    }


def offline(system, cfg: Config, seed: int):
    t0 = time.process_time()
    data, _ = generate_data(system, seed, cfg.generate.n_simulations, max_cost=cfg.max_cost)
    t1 = time.process_time()
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max, seed=seed)
    t2 = time.process_time()
    functions = fit_functions(system, cleaned, cfg)
    t3 = time.process_time()
    return data, cleaned, functions, (t1 - t0, t2 - t1, t3 - t2)


def main() -> None:
    long_runs = "--skip-long" not in sys.argv
    extra = {}
    if long_runs:  # first, on an otherwise idle machine: it measures two workers' speed-up
        import parallel_bench

        extra |= parallel_bench.main()
    systems, limits = None, []
    if "--skip-systems" not in sys.argv:
        systems = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("systems_bench.py")), "--quick"],
            stdout=subprocess.PIPE, text=True)
    if "--skip-limits" not in sys.argv:
        import limits_bench

        # the torque-limit table (a model per row) replaces the truncation-only u1/u2 rows
        # this bench had; two processes, each a share of the rows (their stderr is the
        # per-row progress); LIMIT_QUERIES per row keeps make bench within 5 minutes
        # (`make bench-limits`: 100 per row)
        limits = [subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("limits_bench.py")), "--queries",
             str(LIMIT_QUERIES), "--rows", ",".join(group)], stdout=subprocess.PIPE,
            text=True)
            for group in limits_bench.MAKE_BENCH_GROUPS]
    system = make("pendulum")
    cfg = resolve(Config(), system)  # the library's defaults, derived for the pendulum
    small, _ = generate_data(system, 0, 500)  # warm-up: load compiled kernels
    clean_data(small)
    times = []
    models = []
    for r in range(REPEATS):
        data, cleaned, functions, t = offline(system, cfg, seed=1 + r)
        times.append(t)
        models.append(FittedModel(system, cfg, functions, float(cleaned.duration.max()),
                                  cfg.generate.max_state_distance))
        print(f"offline repeat {r}: generate {t[0]:.2f} s, clean {t[1]:.2f} s, "
              f"fit {t[2]:.2f} s CPU", file=sys.stderr)
    gen, cln, fit = (statistics.median(x) for x in zip(*times, strict=True))
    model = models[-1]
    # the planning figures pool 100 queries on each of the 3 epochs' models: one dataset's
    # median moves by several ms from one epoch to the next
    main_stats = plan_stats(models, "")
    obstacle_stats = plan_stats(model, "obstacle_", obstacles=[BLOCKING_BOX])
    held, _ = generate_data(system, 123_456, 2000, max_cost=cfg.max_cost)
    err = held_out_errors(system, functions, held, n_queries=1000)

    result = {
        "offline_cpu_s": round(gen + cln + fit, 3),
        "generate_cpu_s": round(gen, 3),
        "clean_cpu_s": round(cln, 3),
        "fit_cpu_s": round(fit, 3),
        "raw_points": len(data),
        "kept_points": len(cleaned),
        "plan_success_rate": main_stats.pop("success_rate"),
        "plan_cpu_s_median_per_epoch": main_stats.pop("plan_cpu_s_median_per_epoch"),
        "plan_max_abs_u": main_stats.pop("max_abs_u"),
        **main_stats,
        "steer_mse_median": float(f"{np.median(err.steer_mse):.3g}"),
        "cost_rel_error_median": float(f"{np.median(err.cost_rel_error):.3g}"),
        "held_out_accepted_fraction": round(err.accepted_fraction, 4),
        **obstacle_stats,
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
    if long_runs:
        import soak

        extra |= soak.main(SOAK_QUERIES)
        for key, value in extra.items():
            print(f"{key:28s} {value!s:>12s}")
        print(f"{'gen_speedup_2w target':28s} {'>= 1.7':>12s}  "
              f"{'met' if extra['gen_speedup_2w'] >= 1.7 else 'NOT met'}")
    if systems is not None:
        out, _ = systems.communicate()
        rows = json.loads(out.strip().splitlines()[-1])["systems"]
        print("per system (quick settings: a lower bound on `python bench/systems_bench.py`):")
        for row in rows:
            print("  " + " ".join(f"{k}={v}" for k, v in row.items()))
        extra["systems"] = rows
    if limits:
        outs = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in limits]
        order = list(limits_bench.ROWS)
        rows = sorted((r for o in outs for r in o["limits"]), key=lambda r: order.index(r["row"]))
        print("torque limits (bench/limits_bench.py; sat-u1-w10-mc2 is left out, see there):")
        print("\n".join("  " + line for line in limits_bench.table(rows).splitlines()))
        extra |= {"limits": rows, **limits_bench.ratio_figures(rows)}
        extra["limits_bench_cpu_s"] = round(sum(
            o["limits_bench_cpu_s"] + o["limits_bench_ompl_children_cpu_s"] for o in outs), 1)
    print(json.dumps(result | extra))


if __name__ == "__main__":
    main()
