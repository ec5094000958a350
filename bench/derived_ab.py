"""The pendulum swing-up with the library's derived settings beside the paper's, side by side
in one process on the same seeds (`make bench-derived`, about 3 minutes).

For each of three epochs (data seeds 1-3): one dataset and model with the paper's settings
(`config.PAPER`: cost bound 2, V threshold 0.5, sigma pi/4 and pi/2, one control sample, no
goal connection), one with every setting derived (`rrtcolearn.derive`), then 100 seeded
swing-up queries (tolerance 0.1, 10 s) on each. ``--u-max 1`` runs the same with the input
limit (saturated). Prints one line per configuration and a JSON line; CPU is thread time.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from rrtcolearn.config import Config, paper_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions, plan, resolve, system_from_config


def model_for(cfg: Config, seed: int) -> FittedModel:
    system = system_from_config(cfg)
    cfg = resolve(cfg, system)
    g = cfg.generate
    data, _ = generate_data(system, seed, g.n_simulations, time_weight=cfg.system.time_weight,
                            max_cost=cfg.max_cost, max_state_distance=g.max_state_distance)
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max, seed=seed,
                            scale=system.metric_scale)
    return FittedModel(system, cfg, fit_functions(system, cleaned, cfg),
                       float(cleaned.duration.max()), g.max_state_distance)


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u-max", type=float, default=None)
    ap.add_argument("--queries", type=int, default=100)
    args = ap.parse_args()
    limit = {} if args.u_max is None else {"u_max": args.u_max}
    configs = {"paper": paper_config(system=limit),
               "derived": Config.model_validate({"system": limit})}
    rows = {name: [] for name in configs}
    derived = {}
    for epoch in (1, 2, 3):
        for name, cfg in configs.items():
            model = model_for(cfg, epoch)
            derived[name] = model.config.derived
            plan(model, [-np.pi, 0], [0, 0], 0.1, seed=10_000)  # warm-up
            rows[name] += [plan(model, [-np.pi, 0], [0, 0], 0.1, seed=s, time_limit=10.0)
                           for s in range(args.queries)]
    out = {}
    for name, plans in rows.items():
        solved = [p for p in plans if p.solved]
        out[name] = {
            "plans": len(plans), "success_rate": len(solved) / len(plans),
            "cpu_s_median": round(float(np.median([p.planning_cpu_s for p in plans])), 5),
            "nodes_median": float(np.median([p.nodes for p in plans])),
            "iterations_median": float(np.median([p.iterations for p in plans])),
            "cost_median": round(float(np.median([p.path_cost for p in solved])), 3)
            if solved else None,
            "connected": sum(bool(p.extra.get("goal_connected")) for p in solved)}
        print(name, out[name])
    out["cpu_ratio_derived_to_paper"] = round(
        out["derived"]["cpu_s_median"] / out["paper"]["cpu_s_median"], 3)
    out["derived_settings"] = derived["derived"]
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
