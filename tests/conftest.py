# ruff: noqa: E402 (the BLAS kernel is pinned before numpy is first imported)
from __future__ import annotations

import os
import platform
import re


def _pin_blas_kernel() -> None:
    """Pin OpenBLAS's kernel to Haswell's where the CPU can run it (AVX2 and FMA).

    The LQR connection's Riccati solve is LAPACK's, and its last bits hang on the kernel
    OpenBLAS picks for the CPU: on an AVX-512 machine it picks SkylakeX, and the recorded
    trees of the cases that connect or try LQR (tests/test_tree_hashes.py) come out
    different, as they do under Sandybridge. The hashes were recorded under Haswell (Zen
    gives the same bits). Set before numpy is first imported; an OPENBLAS_CORETYPE already
    set wins."""
    if "OPENBLAS_CORETYPE" in os.environ or platform.machine() not in ("x86_64", "AMD64"):
        return
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            flags = next((line.split(":", 1)[1].split() for line in f
                          if line.startswith("flags")), [])
    except OSError:
        return
    if "avx2" in flags and "fma" in flags:
        os.environ["OPENBLAS_CORETYPE"] = "Haswell"


_pin_blas_kernel()

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from rrtcolearn.config import paper_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions
from rrtcolearn.systems import make

# Property-based tests run the same examples on every run by default (derandomize: a red CI
# is a reproducible one); `make fuzz` runs the "wide" profile, random and ten times longer.
# Examples found by either are kept as explicit tests (@example or plain tests).
settings.register_profile("ci", derandomize=True, database=None, deadline=None,
                          max_examples=500, print_blob=True,
                          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                 HealthCheck.too_slow])
settings.register_profile("wide", parent=settings.get_profile("ci"), derandomize=False,
                          max_examples=5000)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# `make test` installs every extra; a test skipped because one is missing fails the run
_EXTRAS = re.compile(r"could not import|\b(ompl|casadi|dask|distributed|sklearn|scikit-learn)\b")
_skipped_for_extras: list[str] = []


def _skip_reason(report) -> str:
    longrepr = report.longrepr
    return str(longrepr[2]) if isinstance(longrepr, tuple) else str(longrepr)


def _note_extra_skip(report) -> None:
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = _skip_reason(report)
        if _EXTRAS.search(reason):
            _skipped_for_extras.append(f"{report.nodeid}: {reason}")


def pytest_collectreport(report) -> None:
    _note_extra_skip(report)


def pytest_runtest_logreport(report) -> None:
    _note_extra_skip(report)


def pytest_sessionfinish(session, exitstatus) -> None:
    if _skipped_for_extras and session.exitstatus in (pytest.ExitCode.OK,
                                                      pytest.ExitCode.NO_TESTS_COLLECTED):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter) -> None:
    if _skipped_for_extras:
        terminalreporter.section("skipped for a missing extra: the run fails", red=True)
        for line in _skipped_for_extras:
            terminalreporter.line(line)
        terminalreporter.line('install them: pip install -e ".[test,dask,ompl,direct,mlp]"')


@pytest.fixture(scope="session")
def pendulum():
    return make("pendulum")


@pytest.fixture(scope="session")
def small_dataset(pendulum):
    data, _ = generate_data(pendulum, 7, 400, chunk_size=100)
    return data


@pytest.fixture(scope="session")
def paper_model(pendulum) -> FittedModel:
    """The paper's defaults: 40000 simulations, cleaned with d = 0.05, k-NN m = 3."""
    cfg = paper_config()
    data, _ = generate_data(pendulum, 1, cfg.generate.n_simulations)
    cleaned, _ = clean_data(data, seed=1)
    return FittedModel(pendulum, cfg, fit_functions(pendulum, cleaned, cfg),
                       float(cleaned.duration.max()), cfg.generate.max_state_distance)


def pendulum_rhs_numpy(z: np.ndarray, w: float) -> np.ndarray:
    """The paper's state+costate ODEs (Eqs. 6-7) plus running cost, written independently."""
    th, om, lth, lom = z[0], z[1], z[2], z[3]
    return np.array([om, np.sin(th) - lom, -lom * np.cos(th), -lth, w + 0.5 * lom**2])


def rk4_numpy(z0: np.ndarray, w: float, dt: float, steps: int,
              rhs=pendulum_rhs_numpy) -> np.ndarray:
    """A plain RK4 integrator of ``rhs(z, w)`` (the pendulum's by default), independent of the
    package's compiled one; all (steps+1) states."""
    z = np.array(z0, dtype=float)
    out = [z.copy()]
    for _ in range(steps):
        k1 = rhs(z, w)
        k2 = rhs(z + 0.5 * dt * k1, w)
        k3 = rhs(z + 0.5 * dt * k2, w)
        k4 = rhs(z + dt * k3, w)
        z = z + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(z.copy())
    return np.array(out)


def pendulum_edge(e: dict, w: float, dt: float, u_max: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """An edge of a pendulum plan file re-simulated independently: states (k+1, 2), inputs
    (k+1,) and cost. An extremal edge runs Eqs. 6-7 from its costate (u = -lambda_omega,
    clipped to |u| <= ``u_max`` for a saturated model); a control edge holds its input u in
    theta'' = sin(theta) + u, at cost rate w + u^2/2."""
    steps = round(e["duration"] / dt)
    if e.get("control") is None:
        bound = np.inf if u_max is None else u_max

        def extremal(z, w):
            th, om, lth, lom = z[0], z[1], z[2], z[3]
            u = min(max(-lom, -bound), bound)
            return np.array([om, np.sin(th) + u, -lom * np.cos(th), -lth, w + 0.5 * u * u])

        traj = rk4_numpy(np.r_[e["from"], e["costate"], 0.0], w, dt, steps, rhs=extremal)
        return traj[:, :2], np.clip(-traj[:, 3], -bound, bound), float(traj[-1, 4])
    u = float(e["control"][0])

    def rhs(z, w):
        return np.array([z[1], np.sin(z[0]) + u, w + 0.5 * u * u])

    traj = rk4_numpy(np.r_[e["from"], 0.0], w, dt, steps, rhs=rhs)
    return traj[:, :2], np.full(steps + 1, u), float(traj[-1, 2])
