"""The co-learning loop off against on at equal simulations, side by side in one process on
the same seeds (docs/colearn.md has the table and the command).

Per system: the uniform data (Alg. 2, derived settings, ``--simulations`` simulations, data
seed 1), then

- ``on``: up to ``--rounds`` co-learning rounds of simulations / 10 aimed simulations each
  (`rrtcolearn.data.colearn`, the loop `generate.colearn_rounds` runs), stopping by its rule;
- ``on+shoot``: the same with each aimed start refined by Newton shooting onto its x1
  (``shooting=True``; as many aimed simulations per round; the off arm matches ``on``);
- ``off``: uniform simulations only, as many as ``on`` used in all (the first
  ``--simulations`` of them the same as ``on``'s: one seeded stream).

Each arm is cleaned and fitted as `rrtcolearn run` would (`pipeline.clean_dataset`,
`pipeline.fit_functions`), then measured: the hit rate on one
fixed sample of planner-like pairs (`data.colearn.sample_pairs` from the uniform data, its
own stream; the same pairs for both arms; the loop's tolerance, the median landing error of
the uniform data's functions on its own held-out pairs), held-out J, U and landing errors
(`evaluate.held_out_errors` on uniform simulations of another seed), and the system's default
query planned for ``--seeds`` seeds with an iteration budget (no time limit): success, the
planning CPU median to the first solution, the share of the first path's duration made by
learned (extremal) edges, the first path's cost; and the offline CPU (generation, the loop's
refits, cleaning and fit).

Run from the repository root (``examples`` must be importable)::

    PYTHONPATH=src python bench/colearn_ab.py --systems cartpole --seeds 10 \
        --iterations 5000 --simulations 20000 --set learn.mlp_max_iter=100
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `examples`, `bench` importable

from bench.invariance_ab import duration_share

from rrtcolearn.config import load_config
from rrtcolearn.data.colearn import HELD_PAIRS, colearn, landing_errors, sample_pairs
from rrtcolearn.data.generate import generate_data
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.pipeline import (
    FittedModel,
    clean_dataset,
    fit_functions,
    plan,
    query_states,
    resolve,
    seed_stream,
    simulation_options,
    system_from_config,
)

SYSTEMS = ("examples.sparse_rrt_cartpole:make_cartpole", "cartpole")


def run_system(name: str, n_sims: int, rounds: int, seeds: int, iterations: int,
               data_seed: int = 1, overrides: tuple[str, ...] = ()) -> dict:
    cfg = load_config(overrides=[f'system.name="{name}"', f"generate.n_simulations={n_sims}",
                                 f"seed={data_seed}", *overrides])
    system = system_from_config(cfg)
    cfg = resolve(cfg, system)
    g = cfg.generate
    sim = simulation_options(cfg)
    stream = seed_stream(data_seed, "generate")
    c0 = time.process_time()
    base, _ = generate_data(system, stream, n_sims, **sim)
    base_cpu = time.process_time() - c0  # serial: the simulations ran in this process

    def refit(d):
        return fit_functions(system, clean_dataset(cfg, system, d)[0], cfg)

    c0 = time.process_time()
    on_data, records = colearn(system, base, refit, seed=stream, rounds=rounds,
                               simulations=n_sims // 10, first_id=n_sims, **sim)
    loop_cpu = time.process_time() - c0
    c0 = time.process_time()
    shot_data, shot_records = colearn(system, base, refit, seed=stream, rounds=rounds,
                                      simulations=n_sims // 10, first_id=n_sims,
                                      shooting=True, **sim)
    shot_cpu = time.process_time() - c0
    print("  shooting: rounds " + ", ".join(f"{r.round}: hit {r.hit_rate:.1%}"
                                             for r in shot_records), flush=True)
    extra = sum(r.simulations for r in records)
    c0 = time.process_time()
    off_data, _ = generate_data(system, stream, n_sims + extra, **sim)
    off_cpu = time.process_time() - c0
    held, _ = generate_data(system, seed_stream(data_seed + 100, "generate"), 2000, **sim)
    pairs = sample_pairs(system, base, np.random.default_rng(12345), HELD_PAIRS,
                         g.max_state_distance)
    start, goal = query_states(cfg, system)
    print(f"{system.name}: {n_sims} uniform simulations ({len(base)} points); loop rounds "
          + ", ".join(f"{r.round}: hit {r.hit_rate:.1%}" for r in records)
          + f"; {extra} aimed simulations", flush=True)
    rows = {}
    shot_extra = sum(r.simulations for r in shot_records)
    for arm, data, gen_cpu, n_arm in (("off", off_data, off_cpu, n_sims + extra),
                                      ("on", on_data, base_cpu + loop_cpu, n_sims + extra),
                                      ("on+shoot", shot_data, base_cpu + shot_cpu,
                                       n_sims + shot_extra)):
        c0 = time.process_time()
        functions = refit(data)
        model = FittedModel(system, cfg, functions, functions.max_duration_,
                            g.max_state_distance)
        cpu = time.process_time() - c0
        landing, valid, _ = landing_errors(system, model.functions, pairs,
                                           time_weight=cfg.system.time_weight, dt=g.dt)
        hit = landing <= records[0].tolerance  # the loop's round-0 tolerance, both arms
        err = held_out_errors(system, model.functions, held, n_queries=1000,
                              time_weight=cfg.system.time_weight, dt=g.dt)
        outcomes = []
        for s in range(seeds):
            p = plan(model, start, goal, cfg.plan.goal_tolerance, seed=s, time_limit=None,
                     max_iterations=iterations)
            outcomes.append((bool(p.solved), p.planning_cpu_s, duration_share(p), p.path_cost))
        ok = [o for o in outcomes if o[0]]

        def med(i, ok=ok):
            return float(np.median([o[i] for o in ok])) if ok else None

        row = {"simulations": n_arm, "points": len(data),
               "hit_rate": float(hit.mean()),
               "landing_median": float(np.median(landing)), "V_accepts_pairs": float(valid.mean()),
               "J_rel_error_median": float(np.median(err.cost_rel_error)),
               "U_param_error_median": float(np.median(err.param_error)),
               "U_landing_mse_median": float(np.median(np.nan_to_num(err.steer_mse,
                                                                     nan=np.inf))),
               "success": f"{len(ok)}/{seeds}", "cpu_median_s": med(1),
               "learned_duration_share_median": med(2), "cost_median": med(3),
               "offline_cpu_s": gen_cpu + cpu, "per_seed": outcomes}
        rows[arm] = row
        print(f"  {arm:>8}: hit {row['hit_rate']:.1%} (V accepts {row['V_accepts_pairs']:.1%}), "
              f"J err {row['J_rel_error_median']:.3f}, U err {row['U_param_error_median']:.3f}, "
              f"landing MSE {row['U_landing_mse_median']:.3g}; success {row['success']}, CPU "
              f"median {_f(row['cpu_median_s'])} s, learned share "
              f"{_f(row['learned_duration_share_median'])}, cost {_f(row['cost_median'])}; "
              f"offline {row['offline_cpu_s']:.0f} s CPU", flush=True)
    return {system.name: {"rounds": [r.__dict__ for r in records],
                          "shoot_rounds": [r.__dict__ for r in shot_records], **rows}}


def _f(v) -> str:
    return "-" if v is None else f"{v:.3g}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--simulations", type=int, default=20_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=5000)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a configuration override for every arm, e.g. learn.mlp_max_iter=100")
    args = ap.parse_args(argv)
    out = {}
    for name in args.systems.split(","):
        out.update(run_system(name, args.simulations, args.rounds, args.seeds,
                              args.iterations, overrides=tuple(args.set)))
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
