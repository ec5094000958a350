"""`evaluate` against references that share no code with it: a cart-pole plan written by
hand with the plain RK4 and the textbook dynamics of `tests/references.py` (extremal and
random-control edges) must pass `check_plan` and re-simulate to its recorded ends and
costs; `held_out_errors` on a tiny dataset must give the values worked out by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from tests import references as ref
from tests.conftest import rk4_numpy

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.evaluate import PlanCheckError, check_plan, held_out_errors, resimulate
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems import make

W, DT = 1.0, 0.01


def _cartpole_plan() -> dict:
    """A cart-pole plan file's content built by the reference alone: two extremals (the
    state+costate equations of Pontryagin on Tedrake's dynamics, u* = -B' lambda) and two
    held inputs, each edge from where the one before ended; its goal is where it ends."""
    rhs = ref.state_costate_rhs(ref.cartpole, 1, W)
    x = np.array([0.1, 0.4, -0.3, 0.8])
    path = []
    for costate, control, steps in (([3.0, -5.0, 20.0, -8.0], None, 40),
                                    (None, [6.0], 25),
                                    ([-2.0, 4.0, -15.0, 6.0], None, 30),
                                    (None, [-4.0], 15)):
        if control is None:
            z = ref.rk4(rhs, np.r_[x, costate, 0.0], DT, steps)
            end, cost = z[-1, :4], float(z[-1, -1])
            u = [ref.optimal_input(ref.cartpole, s[:4], s[4:8], 1)[0] for s in z]
        else:
            end = ref.hold(ref.cartpole, x, control, DT, steps)[-1]
            cost, u = steps * DT * (W + 0.5 * control[0] ** 2), control
        path.append({"from": x.tolist(), "to": end.tolist(), "duration": steps * DT,
                     "cost": cost, "costate": costate, "control": control,
                     "params": None if control else [0.0] * 4,
                     "max_abs_u": float(np.abs(u).max())})
        x = end
    return {"system": "cartpole", "start": path[0]["from"], "goal": x.tolist(),
            "goal_tolerance": 0.1, "time_weight": W, "dt": DT, "status": "exact",
            "path": path, "path_cost": sum(e["cost"] for e in path),
            "path_duration": sum(e["duration"] for e in path),
            "max_abs_u": max(e["max_abs_u"] for e in path), "final_goal_distance": 0.0}


def test_a_cartpole_plan_written_by_the_reference_checks_out():
    system = make("cartpole")
    d = json.loads(json.dumps(_cartpole_plan()))
    r = check_plan(system, d)  # every end, cost and |u| within 1e-9 of the reference's
    assert r["edges"] == 4 and r["goal_checked"]
    assert r["path_cost"] == pytest.approx(d["path_cost"], rel=1e-10)
    assert r["max_abs_u"] == pytest.approx(d["max_abs_u"], rel=1e-10)
    assert r["end_goal_distance"] < 1e-9
    s = resimulate(system, d)
    assert s["max_gap"] < 1e-10 and s["max_cost_gap"] < 1e-10
    assert s["path_duration"] == pytest.approx(1.1, rel=1e-12)
    # and a plan of another cart-pole (pole mass 1.1 kg) is refused at its first edge
    other = dict(ref.CARTPOLE, mp=1.1)
    moved = ref.hold(lambda x, u: ref.cartpole(x, u, other), d["path"][1]["from"],
                     d["path"][1]["control"], DT, 25)[-1]
    d["path"][1]["to"] = moved.tolist()
    with pytest.raises(PlanCheckError, match=r"path\[1\]: re-simulated"):
        check_plan(system, d)


# --- held_out_errors on five training rows and three held-out rows, by hand -----------------
# k-NN with m = 2, validity threshold 0.3. Training rows: A, B close together, C, D close
# together, E far from both; held-out h1 next to A and B, h2 next to C and D, h3 far from
# everything (V rejects it).

TRAIN = {  # x0, x1, cost, phi, duration
    "A": ([-1.0, 0.2], [-0.9, 0.4], 0.5, 0.3, 0.4),
    "B": ([-1.02, 0.21], [-0.91, 0.41], 0.7, 0.5, 0.6),
    "C": ([0.1, 1.0], [0.3, 1.1], 1.0, -1.3, 0.3),
    "D": ([0.12, 1.01], [0.31, 1.12], 2.0, 4.6, 0.2),
    "E": ([-3.0, -2.0], [-3.0, -2.0], 3.0, 0.0, 1.0),
}
HELD_OUT = {
    "h1": ([-1.01, 0.2], [-0.9, 0.4], 0.65, 0.42, 0.45),
    "h2": ([0.11, 1.0], [0.3, 1.11], 1.2, 4.7, 0.3),
    "h3": ([-4.0, 2.5], [-4.0, 2.5], 1.0, 0.0, 0.5),
}


def _dataset(rows: dict) -> Dataset:
    x0, x1, cost, phi, duration = (np.array([r[k] for r in rows.values()], dtype=float)
                                   for k in range(5))
    n = len(cost)
    return Dataset(x0=x0, x1=x1, cost=cost, params=phi[:, None], duration=duration,
                   costate=np.zeros((n, 2)), simulation=np.arange(n))


def _by_hand() -> dict:
    """Per accepted held-out row: (steering MSE, cost relative error, parameter error,
    duration error), from the paper's formulas.

    h1: J = (0.5 + 0.7) / 2 = 0.6, phi = 0.4 (the circular mean of 0.3 and 0.5), T = 0.5;
    its costate from phi on H* = 0 (l_th = tan phi, l_om = sin th + sign(cos phi)
    sqrt(sin^2 th + 2 (w + l_th om))), run 50 steps of the paper's Eqs. 6-7.
    h2: J = 1.5, T = 0.25; phi the circular mean of -1.3 and 4.6 = 4.6 - 2 pi, i.e.
    (-1.3 + 4.6 - 2 pi) / 2 = -1.4916 (cos > 0, tan = -12.4): w + l_th om < -11, so no costate
    exists and its MSE is infinite; its parameter error is the way round the circle to
    4.7: 2 pi - (4.7 - phi)."""
    th, om = HELD_OUT["h1"][0]
    lth = math.tan(0.4)
    lom = math.sin(th) + math.sqrt(math.sin(th) ** 2 + 2 * (W + lth * om))
    end = rk4_numpy(np.array([th, om, lth, lom, 0.0]), W, DT, 50)[-1, :2]
    mse1 = float(np.mean((end - np.array(HELD_OUT["h1"][1])) ** 2))
    phi2 = (-1.3 + 4.6 - 2 * math.pi) / 2
    th2, om2 = HELD_OUT["h2"][0]
    assert math.sin(th2) ** 2 + 2 * (W + math.tan(phi2) * om2) < 0  # no costate
    return {"h1": (mse1, abs(0.6 - 0.65) / 0.65, abs(0.4 - 0.42), abs(0.5 - 0.45)),
            "h2": (math.inf, abs(1.5 - 1.2) / 1.2, 2 * math.pi - (4.7 - phi2),
                   abs(0.25 - 0.3))}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_held_out_errors_are_the_values_worked_out_by_hand(seed):
    system = make("pendulum")
    f = LearnedFunctions(n_neighbors=2, validity_threshold=0.3).fit(_dataset(TRAIN), system)
    got = held_out_errors(system, f, _dataset(HELD_OUT), time_weight=W, dt=DT, seed=seed)
    # the rows in the order the seed shuffles them, those V accepts
    names = [list(HELD_OUT)[i] for i in np.random.default_rng(seed).permutation(3)]
    names = [n for n in names if n != "h3"]
    want = np.array([_by_hand()[n] for n in names])
    assert got.accepted_fraction == pytest.approx(2 / 3, rel=1e-15)
    np.testing.assert_allclose(got.steer_mse, want[:, 0], rtol=1e-9)
    np.testing.assert_allclose(got.cost_rel_error, want[:, 1], rtol=1e-12)
    np.testing.assert_allclose(got.param_error, want[:, 2], rtol=1e-12)
    np.testing.assert_allclose(got.duration_error, want[:, 3], rtol=1e-12)
    one = held_out_errors(system, f, _dataset(HELD_OUT), time_weight=W, dt=DT, seed=seed,
                          n_queries=1)
    np.testing.assert_allclose(one.cost_rel_error, want[:1, 1], rtol=1e-12)
    assert one.accepted_fraction == pytest.approx(2 / 3, rel=1e-15)
