"""Learning in x0's body frame (planar rotation) against translation invariance only, side by
side in one process on the same data and seeds (docs/invariance.md has the table).

The dynobench unicycle1_v0 problems parallelpark_0 and kink_0 (bench/ablation.py's rows: the
exact body among the boxes, ball 0.1). One dataset (Alg. 2, ``--simulations`` simulations,
data seed ``--data-seed``, 1 by default; every other setting derived or ``--set``),
cleaned once, then two fits:

- ``translation``: the system with ``planar_rotation=()`` (a local patch), J, U and V learned
  on x1 - x0 along x and y, as before;
- ``rotation``: the system as `build_system` found it: the query in x0's body frame and U's
  (d_x, d_y) turned into it.

Each model plans each problem with the default planner for ``--seeds`` seeds within
``--limit`` s of process CPU (bench/ablation.py's `first_solution`: an unsolved seed counts
as the limit in the CPU median) and reports success, the CPU median to the first solution,
the learned share of the first path's duration and its cost (medians over solved seeds), and
held-out errors (`evaluate.held_out_errors`, 2 000 simulations of data seed 101).

    PYTHONPATH=src python bench/rotation_ab.py [--simulations 1500] [--seeds 20] [--limit 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.ablation import first_solution

from rrtcolearn import dynobench as db
from rrtcolearn.config import load_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import (
    FittedModel,
    fit_functions,
    resolve,
    seed_stream,
    simulation_options,
    system_from_config,
)
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition

PROBLEMS = {"parallelpark": "unicycle1_v0/parallelpark_0", "kink": "unicycle1_v0/kink_0"}


def run(n_sims: int, seeds: int, limit: float, overrides: tuple[str, ...],
        data_seed: int = 1) -> dict:
    cfg = load_config(overrides=['system.name="rrtcolearn.dynobench:unicycle1_v0"',
                                 f"generate.n_simulations={n_sims}", f"seed={data_seed}",
                                 *overrides])
    system = system_from_config(cfg)
    cfg = resolve(cfg, system)
    g = cfg.generate
    options = dict(simulation_options(cfg), chunk_size=g.chunk_size)
    data, _ = generate_data(system, seed_stream(data_seed, "generate"), n_sims, **options)
    held, _ = generate_data(system, seed_stream(101, "generate"), 2000, **options)
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max,
                            method=cfg.clean.method, seed=seed_stream(data_seed, "clean"),
                            scale=system.metric_scale)
    print(f"{system.name}: planar rotation {system.planar_rotation}, {len(data)} points, "
          f"{len(cleaned)} cleaned", flush=True)
    arms = {"translation": dataclasses.replace(system, planar_rotation=()),
            "rotation": system}
    out: dict = {}
    for arm, sys_arm in arms.items():
        c0 = time.process_time()
        functions = fit_functions(sys_arm, cleaned, cfg)
        fit_cpu = time.process_time() - c0
        model = FittedModel(sys_arm, cfg, functions, functions.max_duration_,
                            g.max_state_distance)
        err = held_out_errors(sys_arm, functions, held, n_queries=1000,
                              time_weight=cfg.system.time_weight, dt=g.dt)
        out[arm] = {"fit_cpu_s": fit_cpu, "threshold": float(functions.validity_.threshold),
                    "J_rel_error_median": float(np.median(err.cost_rel_error)),
                    "U_param_error_median": float(np.median(err.param_error)),
                    "U_landing_mse_median": float(np.median(np.nan_to_num(
                        err.steer_mse, nan=np.inf))),
                    "V_accepts": float(err.accepted_fraction), "problems": {}}
        print(f"  {arm}: {json.dumps({k: v for k, v in out[arm].items() if k != 'problems'})}",
              flush=True)
        for name, spec in PROBLEMS.items():
            planning = db.planning_problem(db.read_problem(spec), sys_arm, 0.1)
            planner = RRTCoLearn(planning, functions, model.planner_settings())
            planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded
            rows = [first_solution(planner, s, limit) for s in range(seeds)]
            solved = [r for r in rows if r["solved"]]
            summary = {
                "success": f"{len(solved)}/{seeds}",
                "cpu_median_s": statistics.median(r["cpu_s"] if r["solved"] else limit
                                                  for r in rows),
                "learned_share_median": _median(r["learned_share"] for r in solved),
                "cost_median": _median(r["cost"] for r in solved),
                "duration_median": _median(r["duration"] for r in solved),
                "per_seed": [(r["solved"], r["cpu_s"], r["learned_share"], r["cost"])
                             for r in rows]}
            out[arm]["problems"][name] = summary
            print(f"  {arm} {name}: " + ", ".join(
                f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                for k, v in summary.items() if k != "per_seed"), flush=True)
    return out


def _median(values) -> float:
    v = [x for x in values if x is not None and not np.isnan(x)]
    return float(statistics.median(v)) if v else float("nan")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--simulations", type=int, default=1500)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--limit", type=float, default=20.0, help="process CPU s per plan")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override, e.g. clean.k_max=200")
    ap.add_argument("--data-seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    out = run(args.simulations, args.seeds, args.limit, tuple(args.set), args.data_seed)
    if args.out:
        args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
