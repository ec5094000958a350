"""Exact steering by shooting (the goal connection): solutions are H* = 0 extremals that
re-simulate, with an integrator written here, to the target."""

from __future__ import annotations

import numpy as np
import pytest
from tests.conftest import rk4_numpy
from tests.test_systems_planning import rk4 as di_rk4

from rrtcolearn.planning.shooting import shoot
from rrtcolearn.systems import make

DT = 0.01


def offset_to(target):
    target = np.asarray(target, dtype=float)
    return lambda x: np.atleast_2d(x) - target


def test_double_integrator_reaches_the_target_from_a_crude_guess():
    system = make("double_integrator")
    x0, target = np.array([-0.4, 0.3]), np.array([0.5, 0.0])
    res = shoot(system, x0, np.array([0.3, -0.9]), 0.2, offset_to(target), time_weight=1.0,
                dt=DT, max_duration=5.0, tolerance=1e-3)
    assert res is not None and res.residual <= 1e-3
    lam, valid = system.costate_from_params(x0[None], res.params[None], 1.0)
    assert valid[0]
    lq, lv = lam[0]
    assert abs(1.0 + lq * x0[1] - 0.5 * lv**2) < 1e-9  # H* = 0: a free-final-time extremal
    z = di_rk4(np.r_[x0, lam[0], 0.0], 1.0, DT, res.steps)
    # the duration is rounded to the RK4 grid: at most half a step's motion from the target
    assert np.linalg.norm(z[:2] - target) <= 1e-3 + 0.5 * DT * 2.0


def test_pendulum_recovers_a_known_extremal():
    system = make("pendulum")
    x0, phi, steps = np.array([-2.5, 0.4]), 0.3, 80
    lam, _ = system.costate_from_params(x0[None], np.array([[phi]]), 1.0)
    target = rk4_numpy(np.r_[x0, lam[0], 0.0], 1.0, DT, steps)[-1, :2]
    res = shoot(system, x0, np.array([phi + 0.15]), 0.6, offset_to(target), time_weight=1.0,
                dt=DT, max_duration=3.0, tolerance=1e-4)
    assert res is not None
    lam, _ = system.costate_from_params(x0[None], res.params[None], 1.0)
    end = rk4_numpy(np.r_[x0, lam[0], 0.0], 1.0, DT, res.steps)[-1, :2]
    assert np.linalg.norm(end - target) < 0.01
    assert res.steps == pytest.approx(steps, abs=2)


def test_no_solution_within_the_duration_bound_is_none():
    system = make("double_integrator")
    # 50 m in at most 0.5 s needs forces whose cost rate cannot balance H* = 0 ... and the
    # iteration limit ends the search
    res = shoot(system, np.zeros(2), np.array([0.5, -0.5]), 0.2, offset_to([50.0, 0.0]),
                time_weight=1.0, dt=DT, max_duration=0.5, tolerance=1e-3, max_iterations=5)
    assert res is None


def test_land_puts_an_extremal_on_its_target_after_a_fixed_number_of_steps():
    """`land` finds the costate whose extremal, integrated by a plain RK4 of the paper's
    equations (tests/conftest.py), ends on the target after exactly the given steps, from a
    costate 10% off; the H* = 0 it gives up stays small for a target on an H* = 0 extremal."""
    from rrtcolearn.planning.shooting import land

    sys = make("pendulum")
    x0, lam, steps, dt = np.array([-2.5, 0.3]), np.array([0.8, -1.2]), 130, 0.01
    target = rk4_numpy(np.r_[x0, lam, 0.0], 1.0, dt, steps)[-1, :2]
    found = land(sys, x0, 1.1 * lam, steps, target, time_weight=1.0, dt=dt, tolerance=1e-10)
    assert found is not None
    end = rk4_numpy(np.r_[x0, found, 0.0], 1.0, dt, steps)[-1, :2]
    assert np.abs(end - target).max() < 1e-9
    np.testing.assert_allclose(found, lam, atol=1e-6)  # the extremal through the target


def test_land_returns_none_short_of_its_tolerance():
    """Without the iterations to get below the tolerance it gives None, not a costate that
    misses; with them it lands (the 3 rad in 0.05 s an unbounded pendulum can cover)."""
    from rrtcolearn.planning.shooting import land

    sys = make("pendulum")
    x0, lam0, target = np.array([0.0, 0.0]), np.array([0.1, 0.1]), np.array([0.3, 0.0])
    kw = {"time_weight": 1.0, "dt": 0.01, "tolerance": 1e-10}
    assert land(sys, x0, lam0, 5, target, max_iterations=0, **kw) is None
    found = land(sys, x0, lam0, 5, target, **kw)
    assert found is not None
    end = rk4_numpy(np.r_[x0, found, 0.0], 1.0, 0.01, 5)[-1, :2]
    assert np.abs(end - target).max() < 1e-9


def _solve_reference(a, b):
    """Gaussian elimination with partial pivoting in numpy's elementwise operations (the
    solver before it was compiled): the compiled one must give the same bits."""
    m = np.hstack([a, b[:, None]]).astype(np.float64)
    n = len(b)
    scale = float(np.max(np.abs(a)))
    for k in range(n):
        p = k + int(np.argmax(np.abs(m[k:, k])))
        if not abs(m[p, k]) > 1e-13 * scale:
            return np.linalg.lstsq(a, b, rcond=None)[0]
        if p != k:
            m[[k, p]] = m[[p, k]]
        m[k + 1:] -= (m[k + 1:, k] / m[k, k])[:, None] * m[k]
    x = np.zeros(n)
    for k in range(n - 1, -1, -1):
        acc = m[k, n]
        for j in range(k + 1, n):
            acc -= m[k, j] * x[j]
        x[k] = acc / m[k, k]
    return x


def test_the_compiled_linear_solve_has_the_bits_of_the_elementwise_one():
    from rrtcolearn.planning.shooting import _solve

    rng = np.random.default_rng(0)
    for trial in range(400):
        n = 2 + trial % 6
        a = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 6, size=(n, n))
        if trial % 7 == 0:
            a[:, -1] = 0.0  # the Newton Jacobian's structure: the duration's column
            a[-1, -1] = 0.0
            a[:-1, -1] = rng.normal(size=n - 1)
        b = rng.normal(size=n)
        x = _solve(a.copy(), b.copy())
        assert x.tobytes() == _solve_reference(a, b).tobytes()
        assert np.allclose(a @ x, b, rtol=1e-6, atol=1e-6 * np.abs(a).max())
    # singular: least squares, as before
    a = np.array([[1.0, 2.0], [2.0, 4.0]])
    b = np.array([1.0, 2.0])
    assert np.array_equal(_solve(a, b), np.linalg.lstsq(a, b, rcond=None)[0])


def test_endpoints_interpolate_between_rk4_steps_of_an_integrator_written_here():
    """States and costates at durations between RK4 steps (forwards and backwards), their
    rates, and NaN rows past an integration's end, against `rk4_numpy` and linear
    interpolation by hand."""
    from rrtcolearn.planning.shooting import endpoints

    system = make("pendulum")
    x0 = np.array([-2.5, 0.4])
    for dt in (DT, -DT):
        v = np.array([[0.7, -0.3, 0.0], [0.7, -0.3, 0.004], [-1.2, 0.5, 0.237],
                      [0.1, 0.9, 0.5]])
        z, rate = endpoints(system, x0, v, 1.0, dt)
        for row, (lam1, lam2, t) in enumerate(v):
            k = int(np.floor(t / DT))
            traj = rk4_numpy(np.r_[x0, lam1, lam2, 0.0], 1.0, dt, k + 1)
            frac = t / DT - k
            want = traj[k, :4] + frac * (traj[k + 1, :4] - traj[k, :4])
            assert np.allclose(z[row], want, rtol=1e-12, atol=1e-12)
            assert np.allclose(rate[row], (traj[k + 1, :4] - traj[k, :4]) / DT, rtol=1e-9,
                               atol=1e-9)
    # a costate so large that the integration overflows: that row is NaN, the others not
    v = np.array([[1e200, 1e200, 0.5], [0.7, -0.3, 0.05]])
    z, rate = endpoints(system, x0, v, 1.0, DT)
    assert np.isnan(z[0]).all() and np.isnan(rate[0]).all()
    assert np.isfinite(z[1]).all() and np.isfinite(rate[1]).all()


def test_load_kernels_loads_shootings_compiled_functions_with_a_solves_types():
    """After `load_kernels(..., shooting=True)` (every solve that may shoot, before its
    clock) a shot and a landing add no compiled signature."""
    from rrtcolearn.planning import shooting
    from rrtcolearn.planning.rrt import load_kernels
    from rrtcolearn.planning.shooting import land

    system = make("pendulum")
    load_kernels(system, shooting=True)

    def signatures():
        return [len(shooting._eliminate.signatures), len(shooting._interpolate.signatures)]

    before = signatures()
    assert all(before)
    x0, target = np.array([-2.5, 0.4]), np.array([-2.3, 0.9])
    res = shoot(system, x0, np.array([0.4]), 0.5, offset_to(target), time_weight=1.0, dt=DT,
                max_duration=3.0, tolerance=1e-4)
    assert res is not None
    lam, _ = system.costate_from_params(x0[None], res.params[None], 1.0)
    land(system, x0, lam[0], res.steps, target, time_weight=1.0, dt=DT, tolerance=1e-9)
    land(system, target, lam[0], res.steps, x0, time_weight=1.0, dt=-DT, tolerance=1e-9)
    assert signatures() == before
