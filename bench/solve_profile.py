"""Where one solve's CPU goes on the 4-state systems, and two source trees side by side.

Small k-NN models of the acrobot and the cart-pole (the fit settings of their cases in
tests/tree_cases.py) are fitted once into ``--models``. Each solve plans the system's default
query with its default plan settings for at most ``--iterations`` iterations, no time limit,
so that the same seed grows the same tree on any machine and load.

    # cProfile of one solve, grouped by stage (learned expansion, goal connections, ...)
    python bench/solve_profile.py profile --system acrobot --seed 1
    # CPU per solve of two trees, rounds alternating A, B, A, B...; ratios B / A of the
    # medians, and whether every (system, seed) tree is bit-identical on both
    python bench/solve_profile.py ab --a /tmp/base/src --b src --seeds 1-10 --rounds 3

Each round runs one process per tree (``PYTHONPATH`` its ``src``) that loads both models,
warms each with a throwaway solve, and times process CPU around every solve. The tree
identity compares the hash of `tests.tree_cases.tree_hash` (node states, parents, edge
durations and costs, held inputs, the node and iteration counts) of every solve.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).parents[1]
sys.path.insert(0, str(ROOT))

SYSTEMS = ("acrobot", "cartpole")

# stage -> (module file suffix, function name) whose cumulative time is the stage's; listed
# outermost first: a stage's figure includes the stages nested in it (shooting is also
# called by the funnel connection, whose polish it is)
STAGES = {
    "goal connections (all)": ("planning/rrt.py", "_connect"),
    "funnel build": ("planning/funnel.py", "build"),
    "funnel continuation": ("planning/funnel.py", "steer"),
    "shooting (shoot, every caller)": ("planning/shooting.py", "shoot"),
    "  Newton linear solves": ("planning/shooting.py", "_solve"),
    "  endpoints (RK4 + interpolation)": ("planning/shooting.py", "endpoints"),
    "LQR connection": ("planning/connections.py", "lqr_chain"),
    "expansion (all)": ("planning/rrt.py", "_expand"),
    "learned expansion": ("planning/learned.py", "steer"),
    "  learned draws' edges": ("planning/propagator.py", "extremal_edges"),
    "  learned queries (V in order of J)": ("learn/models.py", "best_valid"),
    "random-control expansion": ("planning/controls.py", "run_batch"),
}


def _case(system: str):
    from tests.tree_cases import CASES

    return next(c for c in CASES if c.name == system)


def fit(models: Path) -> None:
    """The two small models, fitted into ``models`` (skipped where saved already)."""
    from tests.tree_cases import fit_model

    for system in SYSTEMS:
        target = models / system
        if not (target / "model.json").exists():
            fit_model(_case(system), target)


def _load(models: Path, system: str):
    from tests.tree_cases import load_model

    return load_model(_case(system), models / system)


def solve(model, seed: int, iterations: int):
    """One solve of the model's default query: at most ``iterations``, no time limit."""
    from rrtcolearn import pipeline

    start, goal = pipeline.query_states(model.config, model.system)
    return pipeline.plan(model, start, goal, model.config.plan.goal_tolerance, seed,
                         time_limit=None, max_iterations=iterations)


def profile(models: Path, system: str, seed: int, iterations: int) -> dict:
    """cProfile of one solve (after a throwaway one): seconds per stage and in all."""
    model = _load(models, system)
    solve(model, seed, 1)
    prof = cProfile.Profile(time.process_time)
    prof.enable()
    plan = solve(model, seed, iterations)
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = max(ct for (_f, _l, name), (_cc, _nc, _tt, ct, _) in stats.items()
                if name == "plan")
    out = {"system": system, "seed": seed, "status": plan.status,
           "iterations": plan.iterations, "nodes": plan.tree.n_nodes,
           "connection": plan.extra.get("connection"), "total_s": round(total, 3)}
    for stage, (suffix, func) in STAGES.items():
        ct = sum(v[3] for (f, _l, name), v in stats.items()
                 if name == func and f.replace(os.sep, "/").endswith(suffix))
        out[stage] = round(ct, 3)
        print(f"{stage:36s} {ct:7.3f} s  {100 * ct / total:5.1f}%")
    print(f"{'solve (cProfile)':36s} {total:7.3f} s; {plan.status}, {plan.iterations} "
          f"iterations, {plan.tree.n_nodes} nodes, connection {out['connection']}")
    return out


def worker(models: Path, seeds: list[int], iterations: int) -> None:
    """One process's solves: per system and seed the CPU and the tree's hash, as JSON."""
    from tests.tree_cases import tree_hash

    out = {}
    for system in SYSTEMS:
        model = _load(models, system)
        solve(model, seeds[0], 50)  # warm: first calls of the compiled kernels
        for seed in seeds:
            t = time.process_time()
            plan = solve(model, seed, iterations)
            out[f"{system}:{seed}"] = {"cpu": time.process_time() - t,
                                       "hash": tree_hash(plan), "status": plan.status}
    print(json.dumps(out))


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def ab(models: Path, a: str, b: str, seeds: list[int], rounds: int, iterations: int) -> dict:
    """Rounds of one process per tree, alternated; per system the median CPU per solve of
    each tree, the median of the per-seed ratios B / A and whether every tree is the same."""
    import statistics

    runs: dict[str, list[dict]] = {"a": [], "b": []}
    for _ in range(rounds):
        for side, src in (("a", a), ("b", b)):
            env = {**os.environ, "PYTHONPATH": str(Path(src).resolve())}
            res = subprocess.run(
                [sys.executable, __file__, "worker", "--models", str(models), "--seeds",
                 f"{seeds[0]}-{seeds[-1]}", "--iterations", str(iterations)],
                env=env, capture_output=True, text=True, check=True, cwd=ROOT)
            runs[side].append(json.loads(res.stdout.strip().splitlines()[-1]))
    out = {}
    for system in SYSTEMS:
        keys = [f"{system}:{s}" for s in seeds]
        med = {side: {k: statistics.median(r[k]["cpu"] for r in runs[side]) for k in keys}
               for side in runs}
        same = [len({r[k]["hash"] for side in runs for r in runs[side]}) == 1 for k in keys]
        solved = sum(runs["a"][0][k]["status"] == "exact" for k in keys)
        ratios = [med["b"][k] / med["a"][k] for k in keys]
        row = {"a_s": round(statistics.median(med["a"].values()), 3),
               "b_s": round(statistics.median(med["b"].values()), 3),
               "ratio_of_medians": round(statistics.median(med["b"].values())
                                         / statistics.median(med["a"].values()), 3),
               "median_ratio": round(statistics.median(ratios), 3),
               "sum_ratio": round(sum(med["b"].values()) / sum(med["a"].values()), 3),
               "identical_trees": f"{sum(same)}/{len(same)}", "solved": solved}
        out[system] = row
        print(f"{system:9s} CPU per solve (median) A {row['a_s']:.3f} s  B {row['b_s']:.3f} s"
              f"  median per-seed B/A {row['median_ratio']:.3f}  summed B/A "
              f"{row['sum_ratio']:.3f}  identical trees {row['identical_trees']}  "
              f"solved {solved}/{len(keys)}")
    print(json.dumps(out))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("fit", "profile", "ab", "worker"))
    ap.add_argument("--models", default="/tmp/solve_profile_models")
    ap.add_argument("--system", default="acrobot", choices=SYSTEMS)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seeds", default="1-10", help="a range, e.g. 1-10")
    ap.add_argument("--iterations", type=int, default=3000,
                    help="at most this many iterations per solve")
    ap.add_argument("--a", help="the baseline's src directory")
    ap.add_argument("--b", help="the candidate's src directory")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    models = Path(args.models)
    if args.mode == "worker":
        worker(models, _seeds(args.seeds), args.iterations)
        return
    fit(models)
    if args.mode == "profile":
        print(json.dumps(profile(models, args.system, args.seed, args.iterations)))
    elif args.mode == "ab":
        ab(models, args.a, args.b, _seeds(args.seeds), args.rounds, args.iterations)


if __name__ == "__main__":
    main()
