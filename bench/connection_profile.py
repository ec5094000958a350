"""Where a plan's CPU goes until its first solution (issue 31): the learned expansion, the
funnel's build and each goal connection, with how many calls each connection had, how many
of them started an attempt from a node (shooting, the funnel's continuation) and which one
reached the goal (docs/derived_settings.md, "The funnel's switch-on and the connections'
allowance").

The default planner on bench/ablation.py's problems and models (``--models``, fitted there
on first use), one JSON line per seed; thread CPU per component, process CPU for the plan.
The funnel's growth is inside the funnel row's CPU, not its build's (the build is the first
part only).

    PYTHONPATH=src python bench/connection_profile.py [--problems cartpole,acrobot]
        [--seeds 0:5] [--limit 30] [--models /tmp/gb_models]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

from rrtcolearn.planning import connections, learned
from rrtcolearn.planning.termination import TerminationCondition

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ablation  # bench/ablation.py: its problems, models and planners

# component -> [calls, thread CPU s, successes]; "<connection>_attempts": calls that
# started from a node
STATS: dict[str, list] = defaultdict(lambda: [0, 0.0, 0])


def _count(key: str, cpu: float, ok: bool) -> None:
    s = STATS[key]
    s[0] += 1
    s[1] += cpu
    s[2] += bool(ok)


def instrument() -> None:
    """Wrap the strategies' entry points with counters (this process only)."""
    for cls, key in ((connections.ShootingConnection, "shooting"),
                     (connections.FunnelConnection, "funnel")):
        def connect(self, tree, _f=cls.connect, _key=key):
            before = int(self.tried.sum())
            t = time.thread_time()
            found = _f(self, tree)
            cpu = time.thread_time() - t
            _count(_key, cpu, found is not None)
            if int(self.tried.sum()) > before:
                _count(_key + "_attempts", cpu, found is not None)
            return found
        cls.connect = connect

    lqr = connections.LQRConnection.connect

    def lqr_connect(self, tree):
        t = time.thread_time()
        found = lqr(self, tree)
        _count("lqr", time.thread_time() - t, found is not None)
        return found
    connections.LQRConnection.connect = lqr_connect

    steer = learned.LearnedSteering.steer

    def learned_steer(self, *a, **k):
        t = time.thread_time()
        out = steer(self, *a, **k)
        _count("learned", time.thread_time() - t, out[1] is not None)
        return out
    learned.LearnedSteering.steer = learned_steer

    build = connections.FunnelConnection.build.__func__

    def funnel_build(cls, *a, **k):
        t = time.thread_time()
        out = build(cls, *a, **k)
        _count("funnel_build", time.thread_time() - t, False)
        return out
    connections.FunnelConnection.build = classmethod(funnel_build)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default="cartpole,acrobot")
    ap.add_argument("--seeds", default="0:5", help="first:last+1")
    ap.add_argument("--limit", type=float, default=30.0, help="process CPU s per plan")
    ap.add_argument("--models", type=Path, default=Path("/tmp/rrtcolearn_ablation_models"))
    args = ap.parse_args(argv)
    instrument()
    first, last = (int(v) for v in args.seeds.split(":"))
    for name in args.problems.split(","):
        problem = ablation.PROBLEMS[name]
        case, model, _ = ablation.model_for(problem, args.models)
        planning = ablation.planning_problem(name, problem, case, model)
        planner = ablation.make_planner(planning, model, "default")
        planner.solve(TerminationCondition(None, 50), 10_000)  # kernels loaded: not timed
        for seed in range(first, last):
            STATS.clear()
            c0 = time.process_time()
            p = planner.solve(TerminationCondition(None, None, args.limit), seed)
            x = p.extra
            print(json.dumps({
                "problem": name, "seed": seed, "solved": bool(p.solved),
                "cpu_s": round(time.process_time() - c0, 3), "iterations": p.iterations,
                "cost": round(float(p.path_cost), 2) if p.solved else None,
                "connection": x.get("connection"), "switched": x.get("connections_switched_on"),
                "funnel_states": x.get("funnel_states"), "funnel_grown": x.get("funnel_grown"),
                "components": {k: [v[0], round(v[1], 3), v[2]] for k, v in STATS.items()}}),
                flush=True)


if __name__ == "__main__":
    main()
