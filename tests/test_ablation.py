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
