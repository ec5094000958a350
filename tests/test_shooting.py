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
