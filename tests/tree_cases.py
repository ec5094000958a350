"""Fixed planning cases whose trees are hashed (tests/test_tree_hashes.py) and timed
(bench/planner_ab.py): every way the planner grows a tree and finishes, on small models.

Each case is a system with a small dataset (the hash needs a stable tree, not a good plan),
a query, plan settings and a seed, planned for a fixed number of iterations
(``time_limit=None``): the pendulum without input limits (learned steering, shooting and the
goal funnel), with |u| <= 1 (random controls in the compiled batch, the LQR connection) and
with |u| <= 1 and an obstacle (random controls in Python), the shipped cart-pole, acrobot and
quadrotor, and sparse_rrt's cart-pole and acrobot from examples/.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).parents[1]


@dataclass(frozen=True)
class Case:
    """One hashed plan: the model's configuration overrides (``fit``), the plan's overrides
    (``plan``), the query, the seed and the iteration budget."""

    name: str
    fit: tuple[str, ...]
    plan: tuple[str, ...] = ()
    start: tuple[float, ...] | None = None  # None: the system's default query
    goal: tuple[float, ...] | None = None
    goal_tolerance: float | None = None
    obstacles: tuple[dict, ...] = ()
    seed: int = 0
    iterations: int = 500


_PENDULUM = ("generate.n_simulations=3000", "clean.k_max=300")
# k-NN J, U and V (fitted in milliseconds; the derived learner of the 4- and 6-state
# systems is the network, which takes tens of seconds to fit)
_SMALL = ("generate.n_simulations=1500", "clean.k_max=200", 'learn.learner="knn"')

CASES = (
    # learned steering; shooting and a small funnel (the automatic one has 20 000 extremals)
    Case("pendulum", _PENDULUM, ("plan.goal_connect=true", "plan.goal_funnel=200"),
         (-np.pi, 0.0), (0.0, 0.0), 0.05, seed=1, iterations=400),
    # learned steering and the automatic connections (tight goal: the tree keeps growing)
    Case("pendulum_auto", _PENDULUM, (), (-np.pi, 0.0), (0.0, 0.0), 0.005, seed=9,
         iterations=3000),
    # random controls switched on by the stall, the compiled batch, the LQR connection
    Case("pendulum_u1", (*_PENDULUM, "system.u_max=1.0"), (), (-np.pi, 0.0), (0.0, 0.0),
         0.01, seed=2, iterations=1500),
    # the same with an obstacle: random controls in Python (the validity checker is Python)
    Case("pendulum_u1_obstacle", (*_PENDULUM, "system.u_max=1.0"), (), (-np.pi, 0.0),
         (0.0, 0.0), 0.05,
         ({"type": "box", "low": [-2.0, 0.3], "high": [-1.2, 2.5]},), seed=3, iterations=800),
    Case("cartpole", ('system.name="cartpole"', *_SMALL), seed=4, iterations=600),
    Case("acrobot", ('system.name="acrobot"', *_SMALL), seed=5, iterations=600),
    Case("quadrotor", ('system.name="quadrotor"', *_SMALL), seed=6, iterations=600),
    Case("sparse_rrt_cartpole",
         ('system.name="examples.sparse_rrt_cartpole:make_cartpole"', *_SMALL),
         seed=7, iterations=1500),
    Case("sparse_rrt_acrobot",
         ('system.name="examples.sparse_rrt_acrobot:make_acrobot"', *_SMALL),
         seed=8, iterations=1500),
)

# the pendulum cases share their model (configurations equal but for the plan)
_MODELS: dict[tuple[str, ...], object] = {}


def fit_model(case: Case, run_dir: Path):
    """The case's model, generated, cleaned and fitted in ``run_dir`` (once per process for
    equal ``fit`` overrides)."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    if case.fit not in _MODELS:
        if str(ROOT) not in sys.path:  # examples.* systems
            sys.path.insert(0, str(ROOT))
        cfg = load_config(overrides=list(case.fit))
        run_dir.mkdir(parents=True, exist_ok=True)
        pipeline.generate(cfg, run_dir)
        pipeline.clean(cfg, run_dir)
        _MODELS[case.fit] = pipeline.fit(cfg, run_dir)
    return _MODELS[case.fit]


def load_model(case: Case, run_dir: Path):
    """The case's model from ``run_dir`` (fitted there before by `fit_model`)."""
    from rrtcolearn import pipeline

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return pipeline.load_model(run_dir)


def plan_case(case: Case, model):
    """The case's plan: ``case.iterations`` iterations, no time limit."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    base = model.config
    cfg = load_config(None, list(case.plan),
                      base={"plan": base.plan.model_dump(),
                            "system": base.system.model_dump(exclude_none=True)})
    cfg = base.model_copy(update={"plan": cfg.plan})
    start, goal = pipeline.query_states(cfg, model.system)
    start = list(case.start) if case.start is not None else start
    goal = list(case.goal) if case.goal is not None else goal
    tol = case.goal_tolerance if case.goal_tolerance is not None else cfg.plan.goal_tolerance
    return pipeline.plan(model, start, goal, tol, case.seed, config=cfg, time_limit=None,
                         max_iterations=case.iterations,
                         obstacles=[dict(o) for o in case.obstacles])


def tree_hash(plan) -> str:
    """A short hash of the whole tree (node states, parents, edge durations and costs, held
    inputs) and the iteration count: equal on two commits that grew the same tree."""
    t, n = plan.tree, plan.tree.n_nodes
    h = hashlib.sha256()
    for a in (t.states[:n], t.parents[:n], t.durations[:n], t.costs[:n], t.controls[:n]):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(str((n, plan.iterations)).encode())
    return h.hexdigest()[:16]


def summary(plan) -> dict:
    """What the case exercised: nodes, iterations, status, edges by kind, the connections
    switched on, the LQR tries and the connection that reached the goal."""
    x = plan.extra
    return {"nodes": plan.tree.n_nodes, "iterations": plan.iterations, "status": plan.status,
            "edges_by": x.get("edges_by"), "switched": x.get("connections_switched_on"),
            "lqr": x.get("goal_lqr"), "connection": x.get("connection"),
            "funnel_states": x.get("funnel_states")}
