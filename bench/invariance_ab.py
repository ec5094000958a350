"""Learning on the invariant coordinates' differences, on against off, side by side in one
process on the same data and seeds (docs/invariance.md has the table and the command).

Per system: one dataset (Alg. 2, derived settings, ``--simulations`` simulations, data seed
1), then three models:

- ``off``: the system with no invariant coordinates (a local patch: the same system with
  ``invariant_coordinates=()``), J, U and V learned on the raw (x0, x1), as before;
- ``on``: the system as `build_system` found it, learned on x1_i - x0_i;
- ``on, x0_i = 0``: the same data with every simulation shifted along its invariant
  coordinates so that it starts at x0_i = 0 (by the invariance, the simulations Alg. 2 would
  have run from x0_i = 0, up to rounding), cleaned and learned again: what sampling x0_i at
  0 instead of over the box would change (only Alg. 3, which compares raw (x0, x1)).

Each model plans the system's default query for ``--seeds`` seeds with an iteration budget
(no time limit, so the outcome does not depend on the machine's load) and reports success,
the planning CPU median to the first solution, the share of the first path's duration made
by extremal (learned) edges, the path cost, held-out J and U errors
(`rrtcolearn.evaluate.held_out_errors`, on simulations of another seed) and the offline CPU
(generation + cleaning + fit, process and worker CPU). ``--pendulum-hash`` prints a hash of
a pendulum tree instead (the same before and after this change: no invariant coordinate).

Run from the repository root (``examples`` must be importable)::

    PYTHONPATH=src python bench/invariance_ab.py --seeds 10 --iterations 5000 \
        --simulations 20000 --set learn.mlp_max_iter=100
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `examples` importable

from rrtcolearn.config import load_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import (
    FittedModel,
    fit_functions,
    plan,
    query_states,
    resolve,
    seed_stream,
    simulation_options,
    system_from_config,
)

SYSTEMS = ("cartpole", "examples.sparse_rrt_cartpole:make_cartpole")


def at_zero(data: Dataset, invariant: tuple[int, ...]) -> Dataset:
    """The data with each row shifted along the invariant coordinates by -x0_i."""
    shift = np.zeros_like(data.x0)
    shift[:, list(invariant)] = -data.x0[:, list(invariant)]
    return dataclasses.replace(data, x0=data.x0 + shift, x1=data.x1 + shift)


def duration_share(p) -> float:
    """Share of the path's duration made by extremal edges (NaN controls)."""
    t, nodes = p.tree, p.path_nodes[1:]
    if not nodes:
        return float("nan")
    dur = t.durations[nodes]
    extremal = np.all(np.isnan(t.controls[nodes]), axis=1)
    return float(dur[extremal].sum() / dur.sum())


def tree_hash(p) -> str:
    t, n = p.tree, p.tree.n_nodes
    h = hashlib.sha256()
    for a in (t.states[:n], t.parents[:n], t.costs[:n], t.durations[:n]):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def offline(cfg, system, data: Dataset, seed: int) -> tuple[FittedModel, float]:
    """Clean and fit ``data`` for ``system``; (model, process CPU s)."""
    c0 = time.process_time()
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max, method=cfg.clean.method,
                            seed=seed_stream(seed, "clean"), scale=system.metric_scale)
    functions = fit_functions(system, cleaned, cfg)
    model = FittedModel(system, cfg, functions, functions.max_duration_,
                        cfg.generate.max_state_distance)
    return model, time.process_time() - c0


def run_system(name: str, n_sims: int, seeds: int, iterations: int, data_seed: int = 1,
               overrides: tuple[str, ...] = ()) -> dict:
    cfg = load_config(overrides=[f'system.name="{name}"', f"generate.n_simulations={n_sims}",
                                 f"seed={data_seed}", *overrides])
    system = system_from_config(cfg)
    cfg = resolve(cfg, system)
    g = cfg.generate
    options = dict(simulation_options(cfg), chunk_size=g.chunk_size)
    c0 = time.process_time()
    data, stats = generate_data(system, seed_stream(data_seed, "generate"), n_sims, **options)
    gen_cpu = time.process_time() - c0 + stats.worker_cpu_s
    held, _ = generate_data(system, seed_stream(data_seed + 100, "generate"), 2000, **options)
    start, goal = query_states(cfg, system)
    inv = system.invariant_coordinates
    print(f"{system.name}: invariant coordinates {inv} "
          f"({', '.join(system.state_names[i] for i in inv)}); {len(data)} points, "
          f"generation {gen_cpu:.1f} s CPU", flush=True)
    arms = {"off": (dataclasses.replace(system, invariant_coordinates=()), data),
            "on": (system, data),
            "on, x0_i = 0": (system, at_zero(data, inv))}
    rows = {}
    for arm, (sys_arm, d) in arms.items():
        model, cpu = offline(cfg, sys_arm, d, data_seed)
        err = held_out_errors(sys_arm, model.functions, held, n_queries=1000,
                              time_weight=cfg.system.time_weight, dt=g.dt)
        outcomes = []
        for s in range(seeds):
            p = plan(model, start, goal, cfg.plan.goal_tolerance, seed=s, time_limit=None,
                     max_iterations=iterations)
            outcomes.append((p.solved, p.planning_cpu_s, duration_share(p), p.path_cost,
                             p.iterations, float(p.tree.durations[p.path_nodes[1:]].sum())))
        ok = [o for o in outcomes if o[0]]
        row = {
            "success": f"{len(ok)}/{seeds}",
            "cpu_median_s": float(np.median([o[1] for o in ok])) if ok else None,
            "learned_duration_share_median": float(np.median([o[2] for o in ok])) if ok
            else None,
            "cost_median": float(np.median([o[3] for o in ok])) if ok else None,
            "iterations_median": float(np.median([o[4] for o in ok])) if ok else None,
            "path_duration_median": float(np.median([o[5] for o in ok])) if ok else None,
            "J_rel_error_median": float(np.median(err.cost_rel_error)),
            "U_param_error_median": float(np.median(err.param_error)),
            # a landing that is not finite counts as a miss (inf)
            "U_landing_mse_median": float(np.median(np.nan_to_num(err.steer_mse,
                                                                  nan=np.inf))),
            "V_accepts": float(err.accepted_fraction),
            "threshold": float(model.functions.validity_.threshold),
            "offline_cpu_s": gen_cpu + cpu,
            "per_seed": outcomes,
        }
        rows[arm] = row
        print(f"  {arm:>13}: success {row['success']}, CPU median {_f(row['cpu_median_s'])} s, "
              f"learned share {_f(row['learned_duration_share_median'])}, cost "
              f"{_f(row['cost_median'])}, duration {_f(row['path_duration_median'])} s, "
              f"J err {row['J_rel_error_median']:.3f}, U err "
              f"{row['U_param_error_median']:.3f}, landing MSE {row['U_landing_mse_median']:.3g}, "
              f"V accepts {row['V_accepts']:.2f} "
              f"(threshold {row['threshold']:.3g}), offline {row['offline_cpu_s']:.0f} s",
              flush=True)
    return {system.name: rows}


def _f(v) -> str:
    return "-" if v is None else f"{v:.3g}"


def pendulum_hash(iterations: int = 3000) -> str:
    """A pendulum tree's hash on a small model (pendulum: no invariant coordinate)."""
    cfg = load_config(overrides=['system.name="pendulum"', "generate.n_simulations=4000"])
    system = system_from_config(cfg)
    cfg = resolve(cfg, system)
    g = cfg.generate
    data, _ = generate_data(system, seed_stream(1, "generate"), g.n_simulations,
                            time_weight=cfg.system.time_weight, dt=g.dt, max_cost=cfg.max_cost,
                            max_state_distance=g.max_state_distance)
    model, _ = offline(cfg, system, data, 1)
    start, goal = query_states(cfg, system)
    out = []
    for tolerance in (cfg.plan.goal_tolerance, 1e-4):  # solved; grown to the budget
        p = plan(model, start, goal, tolerance, seed=3, time_limit=None,
                 max_iterations=iterations)
        out.append(f"tolerance {tolerance:g}: {p.tree.n_nodes} nodes, {p.status}, "
                   f"tree {tree_hash(p)}")
    return "pendulum " + "; ".join(out)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--simulations", type=int, default=20_000)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=5000)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override for every arm, e.g. learn.mlp_max_iter=100")
    ap.add_argument("--pendulum-hash", action="store_true")
    args = ap.parse_args(argv)
    if args.pendulum_hash:
        print(pendulum_hash(), flush=True)
        return {}
    out = {}
    for name in args.systems.split(","):
        out.update(run_system(name, args.simulations, args.seeds, args.iterations,
                              overrides=tuple(args.set)))
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
