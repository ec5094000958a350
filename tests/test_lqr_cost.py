"""The LQR connection's cost-aware ladder (planning/lqr.py: `ladder_weights`,
`GoalLQR.cheapest`, `GoalLQR.cost_to_go`, `held_gain`; built with ``ladder=True``, as the
planner does only while ``connections.LQR_LADDER`` is on, off by default) on sparse_rrt's
cart-pole (|F| <= 300, R = 1), against independent references: sparse_rrt's equations by
hand (tests/references.py), the RK4 step map linearised in closed form, the Riccati
solutions by a structure-preserving doubling iteration written here (not scipy's Schur
method), and the chain's cost summed here."""

from __future__ import annotations

import importlib
import math
import sys
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from tests import references as ref

from rrtcolearn.planning.lqr import (
    HOLD_FRACTION,
    HORIZON_TIME_CONSTANTS,
    LADDER_STEP,
    GoalLQR,
    build_goal_lqr,
    ladder_weights,
)
from rrtcolearn.planning.problem import PlanningProblem

ROOT = Path(__file__).parents[1]
DT = 0.01
W = 1.0  # the time weight
OPTIMUM = 48.005  # docs/collocation.md: the query's collocation optimum (|F| <= 300)


@pytest.fixture(scope="module")
def cart():
    sys.path.insert(0, str(ROOT))
    try:
        mod = importlib.import_module("examples.sparse_rrt_cartpole")
    finally:
        sys.path.remove(str(ROOT))
    system = mod.make_cartpole()
    problem = PlanningProblem.create(system, mod.START, mod.GOAL, mod.GOAL_RADIUS)
    lqr = build_goal_lqr(problem, DT, np.eye(1), W, ladder=True)
    assert isinstance(lqr, GoalLQR), lqr
    return problem, lqr


def _doubling_dare(A, B, Q, R, iterations=60):
    """P of the discrete algebraic Riccati equation by the structure-preserving doubling
    algorithm (A_k, G_k, H_k; H_k -> P quadratically)."""
    Ak, G, H = A.copy(), B @ np.linalg.solve(R, B.T), Q.copy()
    eye = np.eye(len(A))
    for _ in range(iterations):
        W_ = np.linalg.inv(eye + G @ H)
        Ak, G, H = Ak @ W_ @ Ak, G + Ak @ W_ @ G @ Ak.T, H + Ak.T @ H @ W_ @ Ak
    return 0.5 * (H + H.T)


def _reference():
    """(x_e, A, B, Q, R_bryson) at the upright goal (20, 0, pi, 0), F = 0: the RK4 step map
    of sparse_rrt's equations linearised in closed form, Bryson's weights from the boxes
    (x 30, v 40, theta half a turn, w 2; |F| <= 300)."""
    x_e, u_e = np.array([20.0, 0.0, np.pi, 0.0]), np.zeros(1)
    Ac = ref.complex_step_jacobian(
        lambda x: ref.sparse_rrt_cartpole(x[None], u_e[None].astype(complex))[0], x_e)
    Bc = ref.complex_step_jacobian(
        lambda u: ref.sparse_rrt_cartpole(x_e[None].astype(complex), u[None])[0], u_e)
    A, B, term = np.zeros_like(Ac), np.zeros_like(Bc), np.eye(4)
    for k in range(5):
        A += term / math.factorial(k)
        if k < 4:
            B += DT * term @ Bc / math.factorial(k + 1)
        term = term @ (DT * Ac)
    half = np.array([30.0, 40.0, np.pi, 2.0])
    return x_e, A, B, np.diag(DT / half**2), np.array([DT / 300.0**2])


def test_without_the_ladder_flag_there_are_no_gentler_gains(cart):
    problem, _ = cart
    plain = build_goal_lqr(problem, DT, np.eye(1), W)
    assert isinstance(plain, GoalLQR) and plain.gentler == ()


def test_the_ladder_runs_from_brysons_weight_to_the_running_costs():
    r = ladder_weights(np.array([1e-5]), np.array([1.0]))
    rungs = [1e-5, *[x[0] for x in r]]
    ratios = [b / a for a, b in pairwise(rungs)]
    assert len(r) == math.ceil(math.log(1e5) / math.log(LADDER_STEP))
    assert r[-1][0] == pytest.approx(1.0)
    assert all(q <= LADDER_STEP * (1 + 1e-12) for q in ratios)
    assert max(ratios) / min(ratios) == pytest.approx(1.0)  # geometric
    # an input the running cost prices no dearer than the box stays at Bryson's weight
    r2 = ladder_weights(np.array([1e-2, 1.0]), np.array([1.0, 0.5]))
    assert len(r2) == 2 and all(x[1] == 1.0 for x in r2) and r2[-1][0] == pytest.approx(1.0)
    assert ladder_weights(np.array([1.0]), np.array([1.0])) == []
    assert ladder_weights(np.array([1.0]), np.array([0.1])) == []


def test_the_gentler_gains_solve_their_riccati_equations(cart):
    _, lqr = cart
    x_e, A, B, Q, r_bryson = _reference()
    np.testing.assert_allclose(lqr.x_e, x_e, atol=1e-9)
    want = ladder_weights(r_bryson, np.array([DT * 1.0 / W]))
    assert len(lqr.gentler) == len(want) == 5
    for gain, r in zip(lqr.gentler, want, strict=True):
        np.testing.assert_allclose(gain.input_weight, r, rtol=1e-9)
        R = np.diag(r)
        P = _doubling_dare(A, B, Q, R)
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        np.testing.assert_allclose(gain.K, K, rtol=1e-5, atol=1e-7 * np.abs(K).max())
        np.testing.assert_allclose(gain.P, P, rtol=1e-5, atol=1e-7 * np.abs(P).max())
        rho = np.abs(np.linalg.eigvals(A - B @ K)).max()
        assert gain.spectral_radius == pytest.approx(rho, rel=1e-7) and rho < 1.0
    # the gentler the input weight, the slower the loop
    taus = [g.time_constant(DT) for g in lqr.gentler]
    assert taus == sorted(taus)
    # the cost to go: w e'Pe with the last (the running cost's) gain's P
    x = np.array([[-20.0, 0.0, 3.14, 0.0], [10.0, 2.0, 3.0, 0.1]])
    e = x - x_e
    P = _doubling_dare(A, B, Q, np.diag(want[-1]))
    np.testing.assert_allclose(lqr.cost_to_go(x), W * np.einsum("ij,jk,ik->i", e, P, e),
                               rtol=1e-5)


def _held_reference(A, B, Q, r, hold):
    """(K, P) of the weights (Q, diag r) with the input held for ``hold`` steps: the
    sampled system's step map (A^hold, sum_i<hold A^i B) and weights hold Q, hold R, by the
    doubling solver."""
    Ah = np.linalg.matrix_power(A, hold)
    Bh = sum(np.linalg.matrix_power(A, i) @ B for i in range(hold))
    R = hold * np.diag(r)
    P = _doubling_dare(Ah, Bh, hold * Q, R)
    return np.linalg.solve(R + Bh.T @ P @ Bh, Bh.T @ P @ Ah), P


def test_the_gentler_gains_hold_their_input_for_half_their_fastest_time_constant(cart):
    """Each rung's held gain: its hold is HOLD_FRACTION of the dt-designed closed loop's
    fastest time constant (from its eigenvalues, computed here), in whole steps, and its K
    and P solve the Riccati equation of the sampled system at that hold."""
    _, lqr = cart
    _, A, B, Q, _ = _reference()
    for gain in lqr.gentler:
        R = np.diag(gain.input_weight)
        P = _doubling_dare(A, B, Q, R)
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        fastest = -DT / np.log(np.abs(np.linalg.eigvals(A - B @ K)).min())
        hold = int(HOLD_FRACTION * fastest / DT)
        assert hold > 1 and gain.held is not None and gain.held.hold == hold
        Kh, Ph = _held_reference(A, B, Q, gain.input_weight, hold)
        np.testing.assert_allclose(gain.held.K, Kh, rtol=1e-5, atol=1e-7 * np.abs(Kh).max())
        np.testing.assert_allclose(gain.held.P, Ph, rtol=1e-5, atol=1e-7 * np.abs(Ph).max())


def test_from_the_start_the_cheapest_chain_is_a_gentle_gains_and_under_2x(cart):
    """From the query's start (40 m from the goal, at rest) Bryson's loop does not reach the
    goal ball within 3 s; the cheapest chain of the ladder does, and it is the closed loop
    of its rung's gain under sparse_rrt's equations, costs less than twice the collocation
    optimum, and no more than any other rung's reaching chain."""
    problem, lqr = cart
    x_e, A, B, Q, _ = _reference()
    box = problem.constraint_box

    def in_goal(s):
        return problem.goal_distance(s) <= problem.goal_tolerance

    start = np.asarray(problem.start, dtype=float)
    assert not lqr.run(start, 300, box, in_goal).reached
    out, k = lqr.cheapest(start, 300, box, in_goal)
    assert out.reached and k >= 1
    gain = lqr.gentler[k - 1]
    K, _ = _held_reference(A, B, Q, gain.input_weight, gain.held.hold)
    for i, u in enumerate(out.inputs):
        if i % gain.held.hold == 0:  # recomputed at the start of each hold, else held
            e = out.states[i] - x_e
            want = np.clip(-K @ e, -300.0, 300.0)
            np.testing.assert_allclose(u, want, rtol=0,
                                       atol=1e-5 * (np.abs(K) @ np.abs(e)).max())
        else:
            assert np.array_equal(u, out.inputs[i - 1])
        step = ref.hold(ref.sparse_rrt_cartpole, out.states[i], u, DT, 1)[-1]
        np.testing.assert_allclose(out.states[i + 1], step, rtol=1e-9, atol=1e-9)
    # one input per hold: the chain is some hundreds of edges, not one per RK4 step
    breaks = [0, *np.flatnonzero(np.any(out.inputs[1:] != out.inputs[:-1], axis=1)) + 1,
              len(out.inputs)]
    assert len(breaks) - 1 <= math.ceil(len(out.inputs) / gain.held.hold)
    # each such edge, re-simulated in one call from its start as the plan checks do, gives
    # its states bit for bit
    from rrtcolearn.integrate import propagate

    for a, b in pairwise(breaks):
        again = propagate(problem.system, out.states[a], out.inputs[a], DT, b - a)
        assert np.array_equal(again, out.states[a : b + 1])
    assert np.linalg.norm(out.states[-1] - np.asarray(problem.goal)) <= problem.goal_tolerance
    cost = float(np.sum(DT * (W + 0.5 * out.inputs[:, 0] ** 2)))
    assert lqr.chain_cost(out.inputs) == pytest.approx(cost, rel=1e-12)
    assert cost < 2.0 * OPTIMUM
    # a longer chain costs more in time alone; each rung runs for at most its horizon
    for j, other in enumerate(lqr.gentler, 1):
        steps = min(int(cost / (W * DT)), max(300, math.ceil(
            HORIZON_TIME_CONSTANTS * other.time_constant(DT) / DT)))
        run = lqr.run(start, steps, box, in_goal, gain=other)
        if j != k and run.reached:
            assert cost <= float(np.sum(DT * (W + 0.5 * run.inputs[:, 0] ** 2)))
    # the held chain costs what the rung's one-step loop costs, within 0.1%
    steps = max(300, math.ceil(HORIZON_TIME_CONSTANTS * gain.time_constant(DT) / DT))
    one_step = lqr.run(start, steps, box, in_goal, gain=gain)
    assert one_step.reached and cost == pytest.approx(lqr.chain_cost(one_step.inputs),
                                                      rel=1e-3)
