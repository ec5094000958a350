"""Planning CPU of two source trees side by side on the hashed cases (tests/tree_cases.py).

The models are fitted once (with the current tree) into ``--models``; then rounds alternate
A, B, A, B...: each round runs one process per tree (``PYTHONPATH`` its ``src``), which loads
every model, warms it with a throwaway plan, and plans each case ``--repeats`` times, timing
process CPU around each plan. Prints per case the median CPU of each tree over all its plans,
the ratio B / A and whether the trees' hashes agree, then the ratio of the summed medians.

    python bench/planner_ab.py --a /work/wt-old/src --b src [--rounds 4] [--repeats 3]
                               [--cases pendulum,quadrotor]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).parents[1]
sys.path.insert(0, str(ROOT))


def _model_dir(models: Path, index: int) -> Path:
    return models / f"case{index}"


def fit_all(models: Path) -> None:
    """Fit every case's model into ``models`` (skipped where one is saved already)."""
    from tests.tree_cases import CASES, fit_model

    done: dict[tuple[str, ...], Path] = {}
    for i, case in enumerate(CASES):
        target = _model_dir(models, i)
        if case.fit in done:
            if not target.exists():
                target.symlink_to(done[case.fit].resolve())
            continue
        if not (target / "model.json").exists():
            fit_model(case, target)
        done[case.fit] = target


def worker(models: Path, repeats: int, cases: set[str] | None) -> None:
    """One process's plans: per case the CPU of each plan and the tree's hash, as JSON."""
    from tests.tree_cases import CASES, load_model, plan_case, tree_hash

    out = {}
    for i, case in enumerate(CASES):
        if cases is not None and case.name not in cases:
            continue
        model = load_model(case, _model_dir(models, i))
        plan_case(case, model)  # warm: first calls of this case's kernels
        cpu, digest = [], None
        for _ in range(repeats):
            t = time.process_time()
            plan = plan_case(case, model)
            cpu.append(time.process_time() - t)
            digest = tree_hash(plan)
        out[case.name] = {"cpu": cpu, "hash": digest}
    print(json.dumps(out))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, help="the baseline's src directory")
    ap.add_argument("--b", required=True, help="the candidate's src directory")
    ap.add_argument("--models", default="/tmp/planner_ab_models")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cases", default=None, help="comma-separated case names (default all)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    models = Path(args.models)
    if args.worker:
        worker(models, args.repeats, None if args.cases is None else set(args.cases.split(",")))
        return {}
    models.mkdir(parents=True, exist_ok=True)
    fit_all(models)
    runs: dict[str, list[dict]] = {"a": [], "b": []}
    for _ in range(args.rounds):
        for side in ("a", "b"):
            env = {**os.environ, "PYTHONPATH": str(Path(getattr(args, side)).resolve())}
            res = subprocess.run(
                [sys.executable, __file__, "--a", args.a, "--b", args.b, "--models",
                 str(models), "--repeats", str(args.repeats), "--worker",
                 *(["--cases", args.cases] if args.cases else [])],
                env=env, capture_output=True, text=True, check=True, cwd=ROOT)
            runs[side].append(json.loads(res.stdout.strip().splitlines()[-1]))
    import numpy as np

    out, total = {}, {"a": 0.0, "b": 0.0}
    for name in runs["a"][0]:
        med = {s: float(np.median([c for r in runs[s] for c in r[name]["cpu"]]))
               for s in runs}
        same = len({r[name]["hash"] for s in runs for r in runs[s]}) == 1
        out[name] = {"a_ms": round(1e3 * med["a"], 2), "b_ms": round(1e3 * med["b"], 2),
                     "ratio": round(med["b"] / med["a"], 3), "same_tree": same}
        for s in total:
            total[s] += med[s]
        print(f"{name:22s} A {1e3 * med['a']:8.1f} ms  B {1e3 * med['b']:8.1f} ms  "
              f"B/A {med['b'] / med['a']:.3f}  same tree: {same}")
    ratio = total["b"] / total["a"]
    print(f"summed medians: A {1e3 * total['a']:.1f} ms, B {1e3 * total['b']:.1f} ms, "
          f"B/A {ratio:.3f} ({args.rounds} rounds x {args.repeats} plans per case)")
    out["total_ratio"] = round(ratio, 3)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
