"""Planner iteration cost against tree size: thread CPU per iteration over a window of
iterations starting when the tree first holds 100, 1 000 and 10 000 nodes.

The tree grows towards a goal it cannot reach (tolerance 1e-9) on the paper's pendulum model,
so every iteration is an ordinary one. Prints one line per configuration: the paper's planner
(J queried for every node within reach) and the default (the nearest ``plan.max_candidates``
nodes from the tree's nearest-neighbour index). Usage: python bench/iteration_cost.py
[--window 300] [--sizes 100,1000,10000] [--system NAME | --model RUN_DIR] [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from rrtcolearn.config import paper_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

_WARM = 2000  # iterations of the throwaway solve before a saved model's timed one


class _Probe(TerminationCondition):
    """Stops after the last window; records thread CPU at each window's ends, and per part of
    an iteration its calls and CPU within each window. The parts: a learned expansion
    ("learned"), a random-control one ("control", goal-biased: directed), a compiled batch of
    random-control iterations up to the next goal-biased one ("compiled batch"), one goal
    connection's try ("connect")."""

    def __init__(self, planner: RRTCoLearn, sizes: list[int], window: int):
        super().__init__(time_limit=None)
        self.planner, self.sizes, self.window = planner, sizes, window
        self.marks: dict[int, tuple[int, float]] = {}
        self.result: dict[int, float] = {}
        self.parts: dict[int, dict[str, list[float]]] = {}
        self._open: list[int] = []  # the windows being measured
        self._run = None  # the solve's state, once it starts (its tree's size)
        start = planner.start

        def started(rng):
            self._run = start(rng)
            return self._run
        planner.start = started
        # the strategies' entry points (`contracts.Steering`, `contracts.Connection`)
        if planner.learned is not None:
            planner.learned.steer = self._timed(planner.learned.steer, "learned")
        if planner.controls is not None:
            planner.controls.control_edge = self._timed(planner.controls.control_edge,
                                                        "control")
            planner.controls.run_batch = self._timed(planner.controls.run_batch,
                                                     "compiled batch")
        make = planner.connection

        def connection(*args, **kwargs):
            made = make(*args, **kwargs)
            made.connect = self._timed(made.connect, "connect")
            return made
        planner.connection = connection

    def _timed(self, fn, part: str):
        def timed(*args, **kwargs):
            t = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.thread_time() - t
                for size in self._open:
                    calls_cpu = self.parts[size].setdefault(part, [0, 0.0])
                    calls_cpu[0] += 1
                    calls_cpu[1] += dt
        return timed

    def __call__(self, iterations: int) -> bool:
        nodes = self._run.tree.data.n_nodes if self._run is not None else 1
        t = time.thread_time()
        for size in self.sizes:
            if size not in self.marks and nodes >= size:
                self.marks[size] = (iterations, t)
                self.parts[size] = {}
                self._open.append(size)
            elif size in self.marks and size not in self.result:
                it0, t0 = self.marks[size]
                if iterations - it0 >= self.window:
                    self.result[size] = (t - t0) / (iterations - it0)
                    self._open.remove(size)
        return len(self.result) == len(self.sizes)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=int, default=300)
    ap.add_argument("--sizes", default="100,1000,10000")
    ap.add_argument("--system", default=None, help="another system than the paper's "
                    "pendulum: its model with derived settings, the default planner only")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration override for --system (e.g. plan.control_edges=true: "
                    "random-control edges from the first iteration, one planner throughout)")
    ap.add_argument("--model", default=None, metavar="RUN_DIR",
                    help="a saved run directory's model (and its system) instead of fitting "
                    "one: the default planner only, with --set applied to its plan section")
    ap.add_argument("--seed", type=int, default=1, help="the planner's seed")
    args = ap.parse_args(argv)
    sizes = [int(v) for v in args.sizes.split(",")]
    if args.model is not None:
        return _saved_model(args.model, sizes, args.window, tuple(args.set), args.seed)
    if args.system is not None:
        return _other_system(args.system, sizes, args.window, tuple(args.set))
    system = make("pendulum")
    cfg = paper_config()  # the paper's pendulum model: the iteration cost of its planner
    data, _ = generate_data(system, 1, cfg.generate.n_simulations)
    cleaned, _ = clean_data(data, seed=1)
    model = FittedModel(system, cfg, fit_functions(system, cleaned, cfg),
                        float(cleaned.duration.max()), cfg.generate.max_state_distance)
    problem = PlanningProblem.create(system, [-np.pi, 0.0], [0.0, 0.0], 1e-9)
    out = {}
    for label, k in (("paper (all nodes within reach)", None),
                     (f"default (nearest {cfg.plan.max_candidates})", cfg.plan.max_candidates)):
        c = cfg.model_copy(update={"plan": cfg.plan.model_copy(update={"max_candidates": k})})
        planner = RRTCoLearn(problem, model.functions, model.planner_settings(c))
        probe = _Probe(planner, sizes, args.window)
        planner.solve(probe, seed=1)
        ms = {s: round(1e3 * v, 4) for s, v in probe.result.items()}
        ratio = max(ms.values()) / min(ms.values())
        print(f"{label}: ms per iteration at " + ", ".join(f"{s} nodes {v}" for s, v in
                                                            ms.items())
              + f"; largest/smallest {ratio:.2f} (target <= 2)")
        out[label] = {"ms_per_iteration": ms, "ratio": round(ratio, 3)}
    print(json.dumps(out))
    return out


def _other_system(name: str, sizes: list[int], window: int, overrides: tuple[str, ...] = ()
                  ) -> dict:
    """The default planner's iteration cost on ``name``'s derived model (goal connections
    off: the goal is unreachable and every iteration an ordinary one)."""
    import tempfile

    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    cfg = load_config(overrides=[f'system.name="{name}"', "plan.goal_connect=false",
                                 "plan.goal_funnel=0", *overrides])
    with tempfile.TemporaryDirectory() as run_dir:
        pipeline.generate(cfg, run_dir)
        pipeline.clean(cfg, run_dir)
        model = pipeline.fit(cfg, run_dir)
    start, goal = pipeline.query_states(model.config, model.system)
    problem = PlanningProblem.create(model.system, start, goal, 1e-9,
                                     wrap_goal=model.config.plan.wrap_goal)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings())
    probe = _Probe(planner, sizes, window)
    planner.solve(probe, seed=1)
    ms = {s: round(1e3 * v, 4) for s, v in probe.result.items()}
    ratio = max(ms.values()) / min(ms.values())
    print(f"{name}, derived settings{' ' + ' '.join(overrides) if overrides else ''}: "
          "ms per iteration at "
          + ", ".join(f"{s} nodes {v}" for s, v in ms.items())
          + f"; largest/smallest {ratio:.2f} (target <= 2)")
    parts = _part_costs(probe)
    for size, per in parts.items():
        print(f"  at {size} nodes, per call: " + ", ".join(
            f"{part} {v['ms']} ms ({v['calls']} calls)" for part, v in per.items()))
    out = {name: {"ms_per_iteration": ms, "ratio": round(ratio, 3), "parts": parts}}
    print(json.dumps(out))
    return out


def _saved_model(run_dir: str, sizes: list[int], window: int, overrides: tuple[str, ...] = (),
                 seed: int = 1) -> dict:
    """`_other_system` on the model saved in ``run_dir`` (no data generated or fitted): its
    own plan settings with goal connections off and ``overrides``."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    model = pipeline.load_model(run_dir)
    base = model.config
    cfg = load_config(None, ["plan.goal_connect=false", "plan.goal_funnel=0", *overrides],
                      base={"plan": base.plan.model_dump(),
                            "system": base.system.model_dump(exclude_none=True)})
    cfg = base.model_copy(update={"plan": cfg.plan})
    start, goal = pipeline.query_states(cfg, model.system)
    problem = PlanningProblem.create(model.system, start, goal, 1e-9,
                                     wrap_goal=cfg.plan.wrap_goal)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings(cfg))
    # a throwaway solve first: every kernel's first call (a numba cache load, tens of ms)
    # is paid before the windows, which last a fraction of a second at 100 nodes
    planner.solve(TerminationCondition(None, _WARM), seed=seed + 1)
    probe = _Probe(planner, sizes, window)
    plan = planner.solve(probe, seed=seed)
    ms = {s: round(1e3 * v, 4) for s, v in probe.result.items()}
    name = f"{model.system.name} ({run_dir})"
    print(f"{name}{' ' + ' '.join(overrides) if overrides else ''}: ms per iteration at "
          + ", ".join(f"{s} nodes {v}" for s, v in ms.items())
          + f"; first {max(sizes)} nodes {_tree_hash(plan, max(sizes))}")
    parts = _part_costs(probe)
    for size, per in parts.items():
        print(f"  at {size} nodes, per call: " + ", ".join(
            f"{part} {v['ms']} ms ({v['calls']} calls)" for part, v in per.items()))
    out = {name: {"ms_per_iteration": ms, "parts": parts}}
    print(json.dumps(out))
    return out


def _tree_hash(plan, n: int) -> str:
    """A short hash of the tree's first ``n`` nodes, their parents, costs and durations: the
    same on two commits whose planners grew the same tree (where each stops depends on when
    it asks the termination condition)."""
    import hashlib

    t, n = plan.tree, min(n, plan.tree.n_nodes)
    h = hashlib.sha256()
    for a in (t.states[:n], t.parents[:n], t.costs[:n], t.durations[:n]):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:12]


def _part_costs(probe: _Probe) -> dict:
    """Per window: each part's calls and mean ms per call (the iteration's kinds, whose mix
    changes as the tree grows: a tree near the goal makes learned goal iterations)."""
    return {size: {part: {"calls": c, "ms": round(1e3 * t / c, 4)}
                   for part, (c, t) in per.items() if c}
            for size, per in probe.parts.items()}


if __name__ == "__main__":
    main()
