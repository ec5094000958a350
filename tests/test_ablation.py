"""bench/ablation.py's own arithmetic: the duration shares it reports and the price of a
dynobench reference in our cost (the run itself is a bench, docs/ablation.md)."""

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import yaml

from rrtcolearn import dynobench as db

_spec = importlib.util.spec_from_file_location(
    "ablation", Path(__file__).parents[1] / "bench" / "ablation.py")
ablation = importlib.util.module_from_spec(_spec)
sys.modules["ablation"] = ablation  # its dataclasses look their module up
_spec.loader.exec_module(ablation)


def test_the_extremal_share_adds_shooting_and_funnel_edges_to_the_learned_ones():
    # lqr chains and random controls are held inputs, not extremals
    by = {"control": 0.4, "learned": 0.3, "shooting": 0.2, "lqr": 0.06, "funnel": 0.04}
    learned, extremal = ablation.duration_shares(by)
    assert learned == 0.3
    assert math.isclose(extremal, 0.54)
    assert ablation.duration_shares({"control": 1.0}) == (0.0, 0.0)
    assert all(math.isnan(v) for v in ablation.duration_shares({}))


def test_a_reference_priced_with_no_input_weight_is_dynobenchs_own_duration():
    read = db.read_problem("unicycle1_v0/kink_0")
    d = yaml.safe_load((read.path.parent / "kink_0" / "idbastar_v0_solution_v0.yaml")
                       .read_text())
    cost = ablation.reference_cost(np.array(d["actions"]), read.dt, 1.0, np.zeros((2, 2)))
    assert math.isclose(cost, d["cost"], rel_tol=1e-9)  # dynobench's cost is the duration


def test_a_reference_pays_u_r_u_over_2_per_second_held():
    # two steps of 0.5 s: w T = 2 * 1, and (1^2 * 2 + 0) / 2 * 0.5 + (0 + 3^2 * 1) / 2 * 0.5
    actions = np.array([[1.0, 0.0], [0.0, 3.0]])
    r = np.diag([2.0, 1.0])
    assert math.isclose(ablation.reference_cost(actions, 0.5, 2.0, r), 2.0 + 0.5 + 2.25)


def test_cost_by_kind_splits_a_paths_cost_into_time_and_effort_per_kind():
    """bench/cost_by_kind.py's split, by hand: w = 2; a learned edge (1 s, cost 5), a
    random-control edge (0.5 s, cost 4), a funnel edge (2 s, cost 4.5), and a branch off
    the path that must not count."""
    from rrtcolearn.planning.tree import Plan, PlannerData

    spec = importlib.util.spec_from_file_location(
        "cost_by_kind", Path(__file__).parents[1] / "bench" / "cost_by_kind.py")
    cost_by_kind = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cost_by_kind)
    tree = PlannerData(np.zeros(2), 1, capacity=2)
    lam, p = np.zeros(2), np.zeros(1)
    nan2, nan1 = np.full(2, np.nan), np.full(1, np.nan)
    tree.add(np.ones(2), 0, lam, p, 1.0, 5.0, np.zeros((2, 2)), 0.7)  # 1: learned
    tree.add(np.ones(2), 1, nan2, nan1, 0.5, 4.0, np.zeros((2, 2)), 1.2,
             control=np.array([1.2]))  # 2: control
    tree.add(np.ones(2), 0, nan2, nan1, 9.0, 99.0, np.zeros((2, 2)), 9.0,
             control=np.array([9.0]))  # 3: off the path
    tree.add(np.ones(2), 2, lam, p, 2.0, 4.5, np.zeros((2, 2)), 0.3)  # 4: funnel
    tree.made_by[4] = "funnel"
    plan = Plan("pendulum", np.zeros(2), np.ones(2), 0.1, 2.0, 0.01, "exact", 0.0, 0.0, 1,
                tree, [0, 1, 2, 4])
    rows = cost_by_kind.cost_by_kind(plan, 2.0)
    assert rows == {
        "learned": {"edges": 1, "duration": 1.0, "time": 2.0, "effort": 3.0, "max_abs_u": 0.7},
        "control": {"edges": 1, "duration": 0.5, "time": 1.0, "effort": 3.0, "max_abs_u": 1.2},
        "funnel": {"edges": 1, "duration": 2.0, "time": 4.0, "effort": 0.5, "max_abs_u": 0.3}}
    assert math.isclose(sum(r["time"] + r["effort"] for r in rows.values()), plan.path_cost)


def test_versus_prints_both_runs_and_the_cpu_ratio_per_problem():
    """Two hand-made results files: the ratio is this run's median CPU over the base's, an
    unsolved seed counting as the limit (10 s)."""
    def results(cpus, solved):
        first = {str(i): {"solved": ok, "cpu_s": c, "cost": 2.0 * c if ok else None,
                          "learned_share": 1.0, "extremal_share": 1.0}
                 for i, (c, ok) in enumerate(zip(cpus, solved, strict=True))}
        return {"settings": {"limit": 10.0},
                "problems": {"p": {"optimum": {"value": 1.0},
                                   "modes": {"default": {"first": first, "anytime": {}}}}}}

    base = results([4.0, 8.0, 3.0], [True, True, False])  # median of 4, 8, 10: 8
    new = results([1.0, 2.0, 3.0], [True, True, True])  # median 2
    row = ablation.versus(new, base).splitlines()[-1]
    assert row == "| p | 2/3 -> 3/3 | 8 -> 2 | 0.25 | 12 -> 4 |"
