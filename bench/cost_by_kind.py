"""Where a first path's cost is (issue 31): each first solution's cost split by edge kind
(`PlannerData.kind`: learned, control, shooting, funnel, lqr) and into its time part
(w x duration) and its effort part (the integral of u^T R u / 2, the rest of the edge's
cost); beside it, the |u*| the model's own data use, against the box random controls draw
from.

The problems, models and queries are bench/ablation.py's (the same small models, fitted into
``--models`` once); the planner is the default one. Prints one block per seed and a summary
per problem: the median over solved seeds of each kind's share of the path's cost, and of
the effort's share.

    PYTHONPATH=src python bench/cost_by_kind.py [--problems cartpole,acrobot] [--seeds 5]
        [--limit 20] [--models DIR]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ablation  # bench/ablation.py: its problems, models and queries


def cost_by_kind(plan, time_weight: float) -> dict[str, dict[str, float]]:
    """Per edge kind of ``plan``'s path: edges, duration, time part (w x duration), effort
    part (edge cost minus the time part) and the largest |u_i|."""
    tree, out = plan.tree, {}
    for i in plan.path_nodes[1:]:
        row = out.setdefault(tree.kind(i), {"edges": 0, "duration": 0.0, "time": 0.0,
                                            "effort": 0.0, "max_abs_u": 0.0})
        d, c = float(tree.durations[i]), float(tree.costs[i])
        row["edges"] += 1
        row["duration"] += d
        row["time"] += time_weight * d
        row["effort"] += c - time_weight * d
        row["max_abs_u"] = max(row["max_abs_u"], float(tree.max_abs_u[i]))
    return out


def data_inputs(model) -> np.ndarray:
    """(N, m) u* at the start of every training pair of ``model``: the inputs of the data's
    optimal extremals (each pair starts on a simulated extremal, with its costate)."""
    system, t = model.system, model.functions.training_
    n = system.n_states
    x0 = t["inputs"][:, :n]
    lam, valid = system.costate_from_params(x0, t["targets"][:, :-1],
                                            model.config.system.time_weight)
    return system.optimal_control(x0[valid], lam[valid])


def main(argv: list[str] | None = None) -> None:
    from rrtcolearn.planning.termination import TerminationCondition

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default="cartpole,acrobot,sparse_rrt_cartpole,kink")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--limit", type=float, default=20.0, help="process CPU s per plan")
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    args = ap.parse_args(argv)
    for name in args.problems.split(","):
        problem = ablation.PROBLEMS[name]
        case, model, _ = ablation.model_for(problem, args.models)
        planning = ablation.planning_problem(name, problem, case, model)
        planner = ablation.make_planner(planning, model, "default")
        w = model.config.system.time_weight
        u = np.abs(data_inputs(model))
        box = planner.propagator.control_box
        box = None if box is None else np.vstack(box).T.tolist()
        print(f"== {name}: random controls' box {box}"
              f"; the data's |u*| quantiles 50/90/99%: "
              f"{np.quantile(u, [0.5, 0.9, 0.99], axis=0).T.round(3).tolist()}")
        planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded: not timed
        shares: list[dict[str, float]] = []  # per solved seed: kind -> share of the cost
        for seed in range(args.seeds):
            c0 = time.process_time()
            plan = planner.solve(TerminationCondition(None, None, args.limit), seed)
            cpu = time.process_time() - c0
            if not plan.solved:
                print(f"seed {seed}: not solved in {cpu:.1f} s")
                continue
            total = plan.path_cost
            rows = cost_by_kind(plan, w)
            print(f"seed {seed}: cost {total:.4g}, duration {plan.path_duration:.3g} s, "
                  f"CPU {cpu:.2f} s")
            for kind, r in sorted(rows.items(), key=lambda kv: -(kv[1]["time"]
                                                                  + kv[1]["effort"])):
                share = (r["time"] + r["effort"]) / total
                print(f"  {kind:9s} {r['edges']:4d} edges {r['duration']:7.2f} s  time "
                      f"{r['time']:9.4g}  effort {r['effort']:9.4g}  {share:6.1%} of the "
                      f"cost  max|u| {r['max_abs_u']:.3g}")
            seen = {k: (r["time"] + r["effort"]) / total for k, r in rows.items()}
            seen["(effort)"] = sum(r["effort"] for r in rows.values()) / total
            shares.append(seen)
        kinds = sorted({k for s in shares for k in s})
        print(f"{name}: median share of the cost over {len(shares)} solved seeds: " + ", ".join(
            f"{k} {statistics.median(s.get(k, 0.0) for s in shares):.0%}" for k in kinds)
            if shares else f"{name}: no seed solved")

if __name__ == "__main__":
    main()
