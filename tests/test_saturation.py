"""Saturated optimal control (input limits), checked independently of the generated code.

u* against a brute-force minimisation of H over the input box, the H* = 0 root of
costate_from_params against bisection along the same line or ray, rollout_jit against a
hand-written RK4 of hand-written saturated ODEs, and check_system on limited systems (passes
on the shipped ones, fails on broken ones).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import sympy
from tests.conftest import rk4_numpy

from rrtcolearn.systems import make
from rrtcolearn.systems.check import SystemCheckError, check_system
from rrtcolearn.systems.symbolic import build_system, with_input_limits

W = 1.0
UMAX = 1.0  # the pendulum's torque limit
LOW2, HIGH2 = np.array([0.0, -1.0]), np.array([2.0, 0.5])  # the two-input system's box
R2 = np.array([1.0, 2.0])  # its diagonal R
# limits at about half the median |u*| of costate_from_params samples (w = 1): pendulum 2.0,
# double integrator 1.4, cart-pole 11, acrobot 7
SHIPPED_LIMITS = {"pendulum": 1.0, "double_integrator": 0.7, "cartpole": 6.0, "acrobot": 3.5}


def make_two_input(input_low=tuple(LOW2), input_high=tuple(HIGH2)):
    """x = (q, v, p), q' = v, v' = -sin q - 0.2 v + u1 + 0.5 u2, p' = v cos p + cos(q) u2,
    cost w + u1^2 / 2 + u2^2 (R = diag(1, 2)); B depends on the state, so the costate ODE
    has a term in the clipped u."""
    q, v, p, u1, u2 = sympy.symbols("q v p u1 u2", real=True)
    return build_system(
        "two_input", states=[q, v, p], inputs=[u1, u2],
        drift=[v, -sympy.sin(q) - sympy.Rational(1, 5) * v, v * sympy.cos(p)],
        input_matrix=[[0, 0], [1, sympy.Rational(1, 2)], [0, sympy.cos(q)]],
        input_weight=[[1, 0], [0, 2]], state_low=[-2, -2, -2], state_high=[2, 2, 2],
        input_low=input_low, input_high=input_high)


@pytest.fixture(scope="module")
def pendulum_limited():
    return with_input_limits(make("pendulum"), -UMAX, UMAX)


@pytest.fixture(scope="module")
def two_input():
    return make_two_input()


# --------------------------------------------------------------------------- by hand


def pendulum_u(lam):
    return np.clip(-lam[..., 1], -UMAX, UMAX)


def pendulum_rhs(z, w):
    """theta' = omega, omega' = sin(theta) + u, l_th' = -l_om cos(theta), l_om' = -l_th,
    cost' = w + u^2 / 2, with u = clip(-l_om, -UMAX, UMAX)."""
    th, om, lth, lom = z[0], z[1], z[2], z[3]
    u = min(max(-lom, -UMAX), UMAX)
    return np.array([om, math.sin(th) + u, -lom * math.cos(th), -lth, w + 0.5 * u * u])


def two_input_u(x, lam):
    """clip(-R^-1 B(x)^T lambda) for B = [[0, 0], [1, 1/2], [0, cos q]], R = diag(1, 2)."""
    x, lam = np.atleast_2d(x), np.atleast_2d(lam)
    btl = np.stack([lam[:, 1], 0.5 * lam[:, 1] + np.cos(x[:, 0]) * lam[:, 2]], axis=1)
    return np.clip(-btl / R2, LOW2, HIGH2)


def two_input_rhs(z, w):
    """H = w + u1^2/2 + u2^2 + lq v + lv (-sin q - v/5 + u1 + u2/2) + lp (v cos p + cos(q) u2):
    x' = dH/dlambda, lambda' = -dH/dx at the clipped u."""
    q, v, p, lq, lv, lp = z[:6]
    u1, u2 = two_input_u(z[:3], z[3:6])[0]
    return np.array([
        v,
        -math.sin(q) - 0.2 * v + u1 + 0.5 * u2,
        v * math.cos(p) + math.cos(q) * u2,
        lv * math.cos(q) + lp * math.sin(q) * u2,
        -lq + 0.2 * lv - lp * math.cos(p),
        lp * v * math.sin(p),
        w + 0.5 * u1 * u1 + u2 * u2,
    ])


def rk4(rhs, z0, w, dt, steps):
    return rk4_numpy(z0, w, dt, steps, rhs)


def samples(system, n, seed, w=W):
    """Valid (x, p, lambda) from the sampling boxes through costate_from_params."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(system.state_low, system.state_high, (n, system.n_states))
    p = rng.uniform(system.param_low, system.param_high, (n, system.n_params))
    lam, valid = system.costate_from_params(x, p, w)
    return x[valid], p[valid], lam[valid], valid


def h_star(system, x, lam, u_of, w=W):
    """H at the hand-written clipped control."""
    return system.hamiltonian(x, lam, u_of(x, lam), w)


# --------------------------------------------------------------------------- u* = argmin H


def test_pendulum_u_star_is_the_box_minimiser(pendulum_limited):
    s = pendulum_limited
    rng = np.random.default_rng(0)
    x = rng.uniform(s.state_low, s.state_high, (200, 2))
    lam = rng.normal(size=(200, 2)) * rng.choice([0.3, 3.0, 300.0], size=(200, 1))
    u = s.optimal_control(x, lam)
    assert u.shape == (200, 1)
    assert np.all((u >= -UMAX) & (u <= UMAX))
    np.testing.assert_array_equal(u[:, 0], pendulum_u(lam))  # the clipped law, exactly
    # both limits and the inside occur
    assert (u[:, 0] == -UMAX).sum() > 20 and (u[:, 0] == UMAX).sum() > 20
    assert (np.abs(u[:, 0]) < UMAX).sum() > 20
    grid = np.linspace(-UMAX, UMAX, 4001)
    spacing = grid[1] - grid[0]
    rows = np.repeat(np.arange(200), len(grid))
    h = s.hamiltonian(x[rows], lam[rows], np.tile(grid, 200)[:, None], W).reshape(200, -1)
    best = grid[np.argmin(h, axis=1)]
    h_u = s.hamiltonian(x, lam, u, W)
    scale = W + np.abs(lam).sum(axis=1) * (np.abs(x[:, 1]) + 2.0 + UMAX)
    # no grid torque gives a lower H (beyond rounding), and the best one is u*'s neighbour
    assert np.all(h.min(axis=1) >= h_u - 1e-12 * scale)
    assert np.all(np.abs(best - u[:, 0]) <= spacing)
    # H itself, by hand
    f = np.stack([x[:, 1], np.sin(x[:, 0]) + u[:, 0]], axis=1)
    np.testing.assert_allclose(h_u, W + 0.5 * u[:, 0] ** 2 + (lam * f).sum(axis=1),
                               rtol=1e-12, atol=1e-12)


def test_two_input_u_star_is_the_box_minimiser(two_input):
    s = two_input
    assert s.input_limited
    lo, hi = s.input_limits()
    np.testing.assert_array_equal(lo, LOW2)
    np.testing.assert_array_equal(hi, HIGH2)
    rng = np.random.default_rng(1)
    n = 60
    x = rng.uniform(s.state_low, s.state_high, (n, 3))
    lam = rng.normal(size=(n, 3)) * rng.choice([0.5, 2.0, 20.0], size=(n, 1))
    u = s.optimal_control(x, lam)
    assert u.shape == (n, 2)
    assert np.all((u >= LOW2) & (u <= HIGH2))
    np.testing.assert_allclose(u, two_input_u(x, lam), rtol=1e-13, atol=1e-15)
    for j in range(2):  # each input at both limits and inside
        assert (u[:, j] == LOW2[j]).sum() >= 5 and (u[:, j] == HIGH2[j]).sum() >= 5
        assert ((u[:, j] > LOW2[j]) & (u[:, j] < HIGH2[j])).sum() >= 5
    g1, g2 = np.linspace(LOW2[0], HIGH2[0], 301), np.linspace(LOW2[1], HIGH2[1], 226)
    spacing = np.array([g1[1] - g1[0], g2[1] - g2[0]])
    grid = np.stack([a.ravel() for a in np.meshgrid(g1, g2, indexing="ij")], axis=1)
    rows = np.repeat(np.arange(n), len(grid))
    h = s.hamiltonian(x[rows], lam[rows], np.tile(grid, (n, 1)), W).reshape(n, -1)
    best = grid[np.argmin(h, axis=1)]
    h_u = s.hamiltonian(x, lam, u, W)
    scale = W + 10.0 + 10.0 * np.abs(lam).sum(axis=1)
    assert np.all(h.min(axis=1) >= h_u - 1e-12 * scale)
    # H separates input by input (diagonal R), so the grid's best is u*'s neighbour per input
    assert np.all(np.abs(best - u) <= spacing * (1 + 1e-9))


# --------------------------------------------------------------------------- H* = 0 roots


def _peak(g, lo=-1e8, hi=1e8):
    """Maximiser of a concave g on [lo, hi]: a symmetric log grid, then golden sections."""
    mag = np.logspace(-4, np.log10(hi), 400)
    ts = np.concatenate([-mag[::-1], [0.0], mag])
    ts = ts[(ts >= lo) & (ts <= hi)]
    vals = np.array([g(t) for t in ts])
    i = int(np.argmax(vals))
    a, b = ts[max(i - 1, 0)], ts[min(i + 1, len(ts) - 1)]
    r = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(120):  # 0.618^120 ~ 1e-25 of the bracket
        c, d = b - r * (b - a), a + r * (b - a)
        if g(c) >= g(d):
            b = d
        else:
            a = c
    return 0.5 * (a + b)


def _crossing(g, inside, direction):
    """The root of a concave g between ``inside`` (g > 0) and the side ``direction``
    (+1 right, -1 left), by bracket expansion and bisection; NaN if g stays positive."""
    step = 1.0
    out = inside + direction * step
    while g(out) > 0.0:
        step *= 2.0
        if step > 1e12:
            return math.nan
        out = inside + direction * step
    a, b = inside, out
    for _ in range(200):  # from at most 1e12 wide to below double precision
        mid = 0.5 * (a + b)
        if g(mid) > 0.0:
            a = mid
        else:
            b = mid
    return 0.5 * (a + b)


def test_pendulum_phi_root_against_bisection(pendulum_limited):
    """lambda(phi) = (tan phi, 0) + t (0, 1), t the larger root of H* = 0 where cos phi >= 0,
    the smaller one otherwise."""
    s = pendulum_limited
    rng = np.random.default_rng(2)
    n = 120
    x = rng.uniform(s.state_low, s.state_high, (n, 2))
    phi = rng.uniform(s.param_low, s.param_high, (n, 1))
    lam, valid = s.costate_from_params(x, phi, W)
    two_roots = 0
    for i in range(n):
        lth = math.tan(phi[i, 0])

        def g(t, i=i, lth=lth):
            li = np.array([[lth, t]])
            return float(h_star(s, x[i : i + 1], li, lambda _x, lm: pendulum_u(lm)[:, None])[0])

        t0 = _peak(g)
        top = g(t0)
        if top < -1e-9:  # no costate on this line
            assert not valid[i], (x[i], phi[i])
            continue
        if top <= 1e-9:  # tangent within rounding: either answer is right
            continue
        assert valid[i], (x[i], phi[i], top)
        right, left = _crossing(g, t0, +1), _crossing(g, t0, -1)
        want = right if math.cos(phi[i, 0]) >= 0.0 else left
        assert lam[i, 0] == pytest.approx(lth, rel=1e-12, abs=1e-12)
        assert lam[i, 1] == pytest.approx(want, rel=1e-9, abs=1e-9)
        if right - left > 0.1:
            two_roots += 1  # the side matters: the other root is far from the returned one
            other = left if math.cos(phi[i, 0]) >= 0.0 else right
            assert abs(lam[i, 1] - other) > 0.05
    # enough samples on both sides, with saturated roots (|l_om| > UMAX means u* saturates)
    assert two_roots > 40
    cos_pos = np.cos(phi[valid, 0]) >= 0.0
    assert cos_pos.sum() > 20 and (~cos_pos).sum() > 20
    assert (np.abs(lam[valid, 1]) > UMAX).sum() > 20


def test_two_input_ray_root_against_bisection(two_input):
    """lambda = s d / |d| with s the positive root of H*(s d) = 0 (H*(0) = w > 0)."""
    s = two_input
    rng = np.random.default_rng(3)
    n = 100
    x = rng.uniform(s.state_low, s.state_high, (n, 3))
    p = rng.uniform(s.param_low, s.param_high, (n, 3))
    lam, valid = s.costate_from_params(x, p, W)
    assert 10 < valid.sum() < n  # some directions have no positive root under the limits
    saturated = 0
    for i in range(n):
        d = p[i] / np.linalg.norm(p[i])

        def g(t, i=i, d=d):
            return float(h_star(s, x[i : i + 1], t * d[None], two_input_u)[0])

        root = _crossing(g, 0.0, +1)  # g(0) = w > 0: the unique positive root
        if not math.isfinite(root):
            # H* stays positive along the whole ray (it tends to a positive slope)
            assert not valid[i]
            assert g(1e9) > 0.0
            continue
        assert valid[i], (x[i], p[i], root)
        scale = float(np.linalg.norm(lam[i]))
        assert scale == pytest.approx(root, rel=1e-9, abs=1e-12)
        assert float(lam[i] @ d) > 0.0  # along +d: the positive root
        np.testing.assert_allclose(lam[i], root * d, rtol=1e-9, atol=1e-12)
        if np.any(two_input_u(x[i], lam[i])[0] <= LOW2) or np.any(
                two_input_u(x[i], lam[i])[0] >= HIGH2):
            saturated += 1
    assert saturated > 10


# --------------------------------------------------------------------------- re-simulation


def _switching(system, x, lam, u_of, steps, w=W):
    """Indices of extremals whose hand-computed control switches between free and saturated
    within ``steps`` of 0.01 s."""
    low, high = system.input_limits()
    out = []
    for i in range(len(x)):
        traj = system.rollout_jit(np.r_[x[i], lam[i], 0.0], w, 0.01, steps)
        n = system.n_states
        u = u_of(traj[:, :n], traj[:, n : 2 * n])
        sat = (u <= low) | (u >= high)
        if np.isfinite(traj).all() and np.any(sat[1:] != sat[:-1]):
            out.append(i)
    return out


def test_pendulum_rollout_matches_hand_written_saturated_rk4(pendulum_limited):
    s = pendulum_limited
    x, _, lam, _ = samples(s, 200, 4)
    idx = _switching(s, x, lam, lambda _x, lm: pendulum_u(lm)[:, None], 200)
    assert len(idx) >= 5
    for i in idx[:8]:
        z0 = np.r_[x[i], lam[i], 0.0]
        ref = rk4(pendulum_rhs, z0, W, 0.01, 200)
        got = s.rollout_jit(z0, W, 0.01, 200)
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * (1 + np.abs(ref).max()))


def test_two_input_rollout_matches_hand_written_saturated_rk4(two_input):
    s = two_input
    x, _, lam, _ = samples(s, 200, 5)
    idx = _switching(s, x, lam, two_input_u, 200)
    assert len(idx) >= 5
    for i in idx[:8]:
        z0 = np.r_[x[i], lam[i], 0.0]
        ref = rk4(two_input_rhs, z0, W, 0.01, 200)
        got = s.rollout_jit(z0, W, 0.01, 200)
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * (1 + np.abs(ref).max()))
    # the rhs at single points too, away from the trajectories
    rng = np.random.default_rng(6)
    out = np.empty(7)
    for _ in range(50):
        z = np.r_[rng.uniform(-2, 2, 3), rng.normal(size=3) * 5.0, 0.0]
        s.rhs(z, 0.7, out)
        np.testing.assert_allclose(out, two_input_rhs(z, 0.7), rtol=1e-12, atol=1e-12)


def test_h_star_error_across_switches_is_second_order(pendulum_limited):
    """Across a switch RK4 leaves an O(dt^2) offset in H*, which check_system's rollout check
    relies on: 16-fold smaller steps shrink it about 256-fold (4th order would give 65536,
    1st order 16), on extremals where it exceeds the smooth tolerance 1e-6 (1 + S)."""
    s = pendulum_limited
    x, _, lam, _ = samples(s, 600, 8)
    idx = _switching(s, x, lam, lambda _x, lm: pendulum_u(lm)[:, None], 100)
    ratios, worst = [], 0.0
    for i in idx:
        z0 = np.r_[x[i], lam[i], 0.0]
        drift = []
        for k in (1, 16):
            t = s.rollout_jit(z0, W, 0.01 / k, 100 * k)[::k]
            h = h_star(s, t[:, :2], t[:, 2:4], lambda _x, lm: pendulum_u(lm)[:, None])
            drift.append(np.abs(h).max())
            if k == 1:  # 1 + S, S the size of H's terms (as in check_system)
                u = pendulum_u(t[:, 2:4])
                scale = 1.0 + (W + 0.5 * u**2 + np.abs(t[:, 2] * t[:, 1])
                               + np.abs(t[:, 3] * (np.sin(t[:, 0]) + u))).max()
        worst = max(worst, drift[0] / scale)
        if drift[0] > 1e-6 * scale:
            ratios.append(drift[0] / drift[1])
    # measured on this sample: 83 switching extremals, 24 above 1e-6 (1 + S), ratios from
    # 41 (median 275), worst |H*| / (1 + S) 3.0e-4
    assert len(idx) >= 50 and len(ratios) >= 10
    assert min(ratios) > 8.0
    assert 32.0 < np.median(ratios) < 2048.0
    assert worst < 2e-3


# --------------------------------------------------------------------------- check_system


@pytest.mark.parametrize("name", sorted(SHIPPED_LIMITS))
def test_check_system_passes_on_limited_shipped_systems(name):
    a = SHIPPED_LIMITS[name]
    system = with_input_limits(make(name), -a, a)
    assert system.input_limited
    check_system(system)
    check_system(system, n_samples=100, seed=1, time_weight=0.3)


def test_check_system_passes_on_asymmetric_and_half_bounded_limits(two_input):
    check_system(two_input)
    # one input bounded below only, the other unbounded: the brute force spans a range
    # around the unconstrained minimiser on the open sides
    half = make_two_input(input_low=(0.0, -np.inf), input_high=(np.inf, np.inf))
    assert half.input_limited
    check_system(half, n_samples=100)


def _clip_to(system, low, high):
    free = with_input_limits(system, None, None).optimal_control
    return lambda x, lam: np.clip(free(x, lam), low, high)


@pytest.mark.parametrize("case, match", [
    ("unclipped", r"u\* within input limits"),
    ("tighter clip", r"u\* minimises H"),
    ("unclipped rhs", r"state ODE|costate ODE"),
    ("limits not declared", r"u\* minimises H"),
])
def test_check_system_rejects_broken_saturation(pendulum_limited, case, match):
    good = pendulum_limited
    free = with_input_limits(good, None, None)
    changes = {
        "unclipped": {"optimal_control": free.optimal_control},
        "tighter clip": {"optimal_control": _clip_to(good, -0.8 * UMAX, 0.8 * UMAX)},
        "unclipped rhs": {"rhs": free.rhs},
        "limits not declared": {"input_low": None, "input_high": None},
    }[case]
    with pytest.raises(SystemCheckError, match=match) as info:
        check_system(dataclasses.replace(good, **changes))
    assert "system 'pendulum'" in str(info.value)


def test_check_system_rejects_broken_two_input_clip(two_input):
    # the second input's upper limit taken as 0.25 instead of 0.5
    broken = dataclasses.replace(two_input,
                                 optimal_control=_clip_to(two_input, LOW2, [2.0, 0.25]))
    with pytest.raises(SystemCheckError, match=r"u\* minimises H"):
        check_system(broken)


def test_check_system_rejects_a_rollout_that_does_not_conserve_h_star(pendulum_limited):
    """RK4's first step right, then a costate offset growing with time whatever dt: the
    drift of H* does not fall with dt, across switches or not."""
    good = pendulum_limited

    def drifting(z0, w, dt, n_steps):
        traj = good.rollout_jit(z0, w, dt, n_steps)
        traj[2:, 2] += 1e-3 * dt * np.arange(2, n_steps + 1)
        return traj

    with pytest.raises(SystemCheckError, match=r"H\* conservation"):
        check_system(dataclasses.replace(good, rollout_jit=drifting))
