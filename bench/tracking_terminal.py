"""The tracking controller's terminal cost, measured: the goal test's own squared distance
(the default, `tracking.terminal_cost`) against the goal LQR's Riccati solution (the default
before), per multiple of Bryson's Q.

For each problem of bench/tracking_bench.py (plans from ``--runs-dir``, made there if
missing), the gains are recomputed with each terminal cost and each factor of
`tracking.LADDER` (no self-test) and ``--rollouts`` runs tracked on the plan's model and on
the true system of examples/heavier.py, noise 0.001 and start error 0.01 of the box, seed 0
(as the bench). Prints the share of runs ending within twice the goal tolerance, model /
truth, and one JSON line.

    python bench/tracking_terminal.py [--rollouts 100] [--runs-dir runs/tracking]
                                      [--problems acrobot,cartpole]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).parents[1]
if str(ROOT) not in sys.path:  # bench/ and examples/ from any working directory
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from bench.tracking_bench import OBSTACLE, PROBLEMS, plan_file  # noqa: E402

from rrtcolearn import pipeline, tracking  # noqa: E402
from rrtcolearn.planning.lqr import build_goal_lqr, step_jacobians  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rollouts", type=int, default=100)
    ap.add_argument("--runs-dir", type=Path, default=Path("runs/tracking"))
    ap.add_argument("--problems", default="", help="substrings of the problem names ('': all)")
    args = ap.parse_args()
    wanted = [p for p in args.problems.split(",") if p]
    rows = []
    for name, directory, options, truth_factory in (*PROBLEMS, OBSTACLE):
        if wanted and not any(w in name for w in wanted):
            continue
        d = pipeline.read_plan(plan_file(args.runs_dir, directory, options, name == OBSTACLE[0]))
        system = pipeline.plan_system(d)
        base = tracking.TrackingController.build(system, d, ladder=(1.0,))
        nom, dt = base.nominal, base.nominal.dt
        jac = [step_jacobians(system, x, u, dt)
               for x, u in zip(nom.state[:-1], nom.input[:-1], strict=True)]
        A, B = np.array([a for a, _ in jac]), np.array([b for _, b in jac])
        Q, R = tracking.tracking_weights(base.problem, dt)
        # R / dt: the running cost's weight where an input is unbounded, all the goal LQR
        # reads of it (as `TrackingController.build` passed it before)
        goal = build_goal_lqr(base.problem, dt, np.diag(np.diag(R) / dt))
        terminals = {"diag(w^2) (default)": tracking.terminal_cost(base.problem, dt)[0]}
        if not isinstance(goal, str):
            terminals["goal LQR P (before)"] = goal.P
        for label, P_final in terminals.items():
            for factor in tracking.LADDER:
                cpu = time.process_time()
                K, P = tracking.riccati_gains(A, B, factor * Q, R, P_final)
                c = dataclasses.replace(base, K=K, P=P, state_weight=factor)
                shares = []
                for truth in (None, truth_factory()):
                    _, tr = tracking.rollouts(c, args.rollouts, truth=truth, noise=1e-3,
                                              start_error=0.01, seed=0)
                    shares.append(tracking.summarise(c, tr))
                rows.append({"problem": name, "terminal": label, "state_weight": factor,
                             "model": shares[0], "truth": shares[1]})
                print(f"{name:26s} terminal {label:22s} Q x{factor:<6g} within 2x: model "
                      f"{shares[0]['reached_2x']:.2f}, truth {shares[1]['reached_2x']:.2f} | "
                      f"final error median model {shares[0]['final_error_median']:.3g}, truth "
                      f"{shares[1]['final_error_median']:.3g} | "
                      f"{time.process_time() - cpu:.2f} CPU s", flush=True)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
