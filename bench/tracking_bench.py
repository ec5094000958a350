"""Plans tracked under model error: open-loop against time-varying LQR, side by side.

For each problem a plan is made once (``rrtcolearn run``, or ``plan`` among obstacles, into
``--runs-dir``; an existing plan there is reused), then ``--rollouts`` runs of it open-loop and
tracked (`rrtcolearn.tracking`) on the "true" system of examples/heavier.py (every mass and
length 10% larger, inertias 1.1^3), with process noise ``--noise`` (a fraction of each
state's box width per sqrt(s)) and a start error within +- ``--start-error`` of the box width,
seed 0: the same draws for both. One row for the default (the state weight the model's
self-test picks, `tracking.LADDER`, with the input rule it picks, `tracking.INPUT_RULES`)
and one per fixed weight of ``--weights`` (multiples of Bryson's Q, with Bryson's R from the
input box: 1 is the goal LQR's rule, the default before the self-test). Prints one line per
row and, last, one JSON line.

    python bench/tracking_bench.py [--rollouts 100] [--runs-dir runs/tracking]
                                   [--noise 0.001] [--start-error 0.01]
                                   [--weights 1]

The issue's target: tracked within 2x the goal tolerance >= 95%, inputs always in the box.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).parents[1]
if str(ROOT) not in sys.path:  # examples/ (the true systems) from any working directory
    sys.path.insert(0, str(ROOT))

import examples.heavier as heavier  # noqa: E402

from rrtcolearn import pipeline, tracking  # noqa: E402

# name, run directory, `rrtcolearn run` options, the true system; the cart-pole's and
# acrobot's limits are 50% of the median max |u| of their unbounded plans (docs/systems.md)
PROBLEMS = (
    ("pendulum |u|<=1", "u1", ["--u-max", "1"], heavier.pendulum),
    ("cartpole 50% (219.9 N)", "cart", ["--system", "cartpole", "--set", "system.u_max=219.9"],
     heavier.cartpole),
    ("acrobot 50% (25.2 N m)", "acro", ["--system", "acrobot", "--set", "system.u_max=25.2"],
     heavier.acrobot),
    ("quadrotor", "quad", ["--system", "quadrotor"], heavier.quadrotor),
)
# the pendulum among obstacles: the README's box (and none of the run's), planned with the
# `make run` model
OBSTACLE = ("pendulum, obstacle box", "pendulum-swingup", [], heavier.pendulum)
OBSTACLE_PLAN = ["--start=-3.14159,0", "--goal", "0,0", "--seed", "1",
                 "--obstacle", "box:-2.0,0.3,-1.2,2.5"]


def _rrtcolearn(*args: str) -> None:
    exe = Path(sys.executable).parent / "rrtcolearn"
    subprocess.run([str(exe), *args], check=True, stdout=subprocess.DEVNULL)


def plan_file(runs: Path, directory: str, options: list[str], obstacle: bool) -> Path:
    """The problem's plan, made if missing."""
    run = runs / directory
    if not (run / "plan.json").is_file():
        _rrtcolearn("run", "--out", str(run), *options)
    if not obstacle:
        return run / "plan.json"
    target = run / "obstacle.json"
    if not target.is_file():
        _rrtcolearn("plan", "--model", str(run), *OBSTACLE_PLAN, "--out", str(target))
    return target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rollouts", type=int, default=100)
    ap.add_argument("--runs-dir", type=Path, default=Path("runs/tracking"))
    ap.add_argument("--noise", type=float, default=1e-3)
    ap.add_argument("--start-error", type=float, default=0.01)
    ap.add_argument("--weights", default="1", help="fixed weights to compare ('': none)")
    args = ap.parse_args()
    rows = []
    for name, directory, options, truth_factory in (*PROBLEMS, OBSTACLE):
        path = plan_file(args.runs_dir, directory, options, name == OBSTACLE[0])
        d = pipeline.read_plan(path)
        system = pipeline.plan_system(d)
        truth = truth_factory()
        fixed = [float(v) for v in args.weights.split(",") if v]
        for weight in (None, *fixed):
            cpu = time.process_time()
            c = (tracking.TrackingController.build(system, d) if weight is None else
                 tracking.TrackingController.build(system, d, state_weight=weight,
                                                   ladder=(1.0,), input_rules=("box",)))
            runs = tracking.rollouts(c, args.rollouts, truth=truth, noise=args.noise,
                                     start_error=args.start_error, seed=0)
            ol, tr = (tracking.summarise(c, r) for r in runs)
            cpu = time.process_time() - cpu
            row = {"problem": name, "plan_status": d["status"], "edges": len(d["path"]),
                   "duration_s": round(c.nominal.t[-1], 3),
                   "rule": "self-test" if weight is None else "fixed",
                   "state_weight": c.state_weight, "input_rule": c.input_rule,
                   "open_loop": ol, "tracked": tr, "cpu_s": round(cpu, 2),
                   "terminal": c.terminal}
            rows.append(row)
            rule = "auto" if weight is None else "fixed"
            print(f"{name:26s} {rule} w={c.state_weight:<5g} R {c.input_rule:4s} "
                  f"plan {d['status']:5s} "
                  f"{len(d['path']):3d} edges"
                  f" {c.nominal.t[-1]:5.2f} s | reached / 2x: open-loop {ol['reached']:.2f}"
                  f" / {ol['reached_2x']:.2f}, tracked {tr['reached']:.2f} / "
                  f"{tr['reached_2x']:.2f} | final err median OL {ol['final_error_median']:.3g}"
                  f" TR {tr['final_error_median']:.3g} | at limit TR {tr['time_at_limit']:.2f}"
                  f" | in box {tr['inputs_in_box']} | obstacle entries OL "
                  f"{ol['obstacle_entries']} TR {tr['obstacle_entries']} | constraint exits "
                  f"OL {ol['constraint_exits']} TR {tr['constraint_exits']} | {cpu:.1f} CPU s",
                  flush=True)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
