"""Systems generated from sympy definitions, the numerical system checker, and the double
integrator's closed-form cost-to-go as an oracle for the indirect method."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy

from rrtcolearn.systems import make
from rrtcolearn.systems.check import SystemCheckError, check_system
from rrtcolearn.systems.double_integrator import (
    cost_for_duration,
    make_double_integrator,
    optimal_arrival,
    optimal_cost,
)
from rrtcolearn.systems.pendulum import make_pendulum
from rrtcolearn.systems.symbolic import CostateParametrisation, SymbolicSystem, build_system

KERNELS = ("rhs", "input_max_abs_jit", "costate_from_params_jit", "rollout_jit",
           "rollout_batch_jit")


def direction_pendulum(**kwargs) -> SymbolicSystem:
    """The pendulum's equations with the default (costate direction) parametrisation instead
    of the registered pendulum's phi (not registered)."""
    theta, omega, u = sympy.symbols("theta omega u")
    return build_system(
        "pendulum_direction", [theta, omega], [u], [omega, sympy.sin(theta)], [[0], [1]],
        [[1]], state_low=[-1.5 * np.pi, -np.pi], state_high=[0.5 * np.pi, np.pi],
        angle_dims=[0], **kwargs)


def warm_up(system) -> dict[str, tuple[int, int]]:
    """Call every compiled kernel once; per kernel, numba's (cache hits, cache misses): a miss
    is a compilation, a hit a load from the on-disk cache."""
    n = system.n_states
    z = np.r_[np.full(2 * n, 0.1), 0.0]
    lam = np.empty(n)
    calls = {
        "rhs": lambda: system.rhs(z, 1.0, np.empty(2 * n + 1)),
        "input_max_abs_jit": lambda: system.input_max_abs_jit(z),
        "costate_from_params_jit": lambda: system.costate_from_params_jit(
            z[:n], np.ones(n), 1.0, lam),
        "rollout_jit": lambda: system.rollout_jit(z, 1.0, 0.01, 2),
        "rollout_batch_jit": lambda: system.rollout_batch_jit(
            z[None], 1.0, 0.01, 2, 1e9, 1e9, n, -1.0),
    }
    stats = {}
    for name in KERNELS:
        calls[name]()
        kernel = getattr(system, name).stats
        stats[name] = (sum(kernel.cache_hits.values()), sum(kernel.cache_misses.values()))
    return stats


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    """A fresh generated-module cache for this module (so the first builds compile)."""
    path = tmp_path_factory.mktemp("rrtcolearn-cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RRTCOLEARN_CACHE", str(path))
        yield path


@pytest.fixture(scope="module")
def cold_stats(cache_dir) -> dict[str, dict[str, tuple[int, int]]]:
    return {}


@pytest.fixture(scope="module")
def dir_pendulum(cache_dir, cold_stats) -> SymbolicSystem:
    system = direction_pendulum()
    cold_stats["pendulum_direction"] = warm_up(system)
    return system


@pytest.fixture(scope="module")
def double_integrator(cache_dir, cold_stats) -> SymbolicSystem:
    system = make_double_integrator()
    cold_stats["double_integrator"] = warm_up(system)
    return system


# --------------------------------------------------------------------------- check_system


@pytest.mark.parametrize("which", ["pendulum", "pendulum_direction", "double_integrator"])
def test_check_system_passes(which, request):
    system = {"pendulum": lambda: make("pendulum"),
              "pendulum_direction": lambda: request.getfixturevalue("dir_pendulum"),
              "double_integrator": lambda: request.getfixturevalue("double_integrator")}[which]()
    check_system(system)
    check_system(system, n_samples=100, seed=1, time_weight=0.3)


def _tampered_rhs(rhs, edit):
    def bad(z, w, out):
        rhs(z, w, out)
        edit(z, out)
    return bad


def _flip_costate(z, out):
    out[2:4] *= -1.0


def _cost_plus(z, out):
    out[4] += 0.1 * z[3] ** 2


def _scaled_costates(system, factor):
    def numpy_version(x, p, w):
        lam, valid = system.costate_from_params(x, p, w)
        return lam * factor, valid

    def jit_version(x, p, w, out):
        ok = system.costate_from_params_jit(x, p, w, out)
        out *= factor
        return ok

    return {"costate_from_params": numpy_version, "costate_from_params_jit": jit_version}


@pytest.mark.parametrize("case, match", [
    ("costate sign", r"costate ODE: rhs costate part != -dH\*/dx"),
    ("running cost", r"running cost: rhs last entry"),
    ("off surface", r"H\* = 0"),
    ("wrong u*", r"u\* minimises H|H\* = 0"),
    ("wrong angle", r"angle periodicity"),
    ("shape", r"shapes: hamiltonian returned shape"),
])
def test_check_system_rejects_broken_definitions(case, match):
    good = make("pendulum")
    changes = {
        "costate sign": {"rhs": _tampered_rhs(good.rhs, _flip_costate)},
        "running cost": {"rhs": _tampered_rhs(good.rhs, _cost_plus)},
        "off surface": _scaled_costates(good, 1.01),
        "wrong u*": {"optimal_control": lambda x, lam: 0.9 * good.optimal_control(x, lam)},
        "wrong angle": {"angle_dims": (0, 1)},
        "shape": {"hamiltonian": lambda x, lam, u, w: good.hamiltonian(x, lam, u, w)[:, None]},
    }[case]
    with pytest.raises(SystemCheckError, match=match) as info:
        check_system(dataclasses.replace(good, **changes))
    assert isinstance(info.value, AssertionError)
    assert "system 'pendulum'" in str(info.value)


def test_invalid_definitions_are_rejected(cache_dir):
    q, v, u, k = sympy.symbols("q v u k")
    base = dict(name="bad", states=[q, v], inputs=[u], drift=[v, -k * q],
                input_matrix=[[0], [1]], state_low=[-1, -1], state_high=[1, 1])
    with pytest.raises(ValueError, match="not states: \\['k'\\]"):
        build_system(**base)
    with pytest.raises(ValueError, match="must not depend on the inputs"):
        build_system(**(base | {"drift": [v, u], "parameters": {k: 1.0}}))
    with pytest.raises(ValueError, match="positive definite"):
        build_system(**(base | {"input_weight": [[-1]], "parameters": {k: 1.0}}))
    with pytest.raises(ValueError, match="shape"):
        build_system(**(base | {"input_matrix": [[0, 1], [1, 0]], "parameters": {k: 1.0}}))


# --------------------------------------------------------------------------- pendulum


def test_pendulum_parametrisation_is_the_authors(dir_pendulum, cache_dir):
    """The registered pendulum is the generic system with its own phi parametrisation (its
    equations against the hand-derived ones: test_pmp)."""
    pend = make_pendulum()  # built in this module's cache, like dir_pendulum
    assert pend.param_names == ("phi",) and pend.param_circular == (True,)
    assert dir_pendulum.param_names == ("d_theta", "d_omega")
    assert pend.costate_from_params is not dir_pendulum.costate_from_params
    # costates of either parametrisation lie on H* = 0
    rng = np.random.default_rng(0)
    x = rng.uniform(pend.state_low, pend.state_high, (500, 2))
    for w in (1.0, 0.3):
        for system in (pend, dir_pendulum):
            p = rng.uniform(system.param_low, system.param_high, (500, system.n_params))
            lam, valid = system.costate_from_params(x, p, w)
            assert valid.mean() > 0.5
            lv, xv = lam[valid], x[valid]
            h = pend.hamiltonian(xv, lv, pend.optimal_control(xv, lv), w)
            assert np.all(np.abs(h) <= 1e-9 * (1.0 + np.sum(lv * lv, axis=1)))
        # a direction and any positive multiple of it give the same costate
        p = rng.uniform(-1.0, 1.0, (500, 2))
        lam, valid = dir_pendulum.costate_from_params(x, p, w)
        assert valid.mean() > 0.99  # invalid only when d_omega ~ 0 and d.a(x) >= 0
        lam2, _ = dir_pendulum.costate_from_params(x, 0.37 * p, w)
        np.testing.assert_allclose(lam2[valid], lam[valid], rtol=1e-12)


def test_costate_parametrisation_is_validated():
    from rrtcolearn.systems.pendulum import phi_inverse, phi_line

    good = dict(names=("phi",), low=(0.0,), high=(1.0,), circular=(True,), line=phi_line,
                inverse=phi_inverse)
    cp = CostateParametrisation(**(good | {"low": np.array([0.0]), "names": ["phi"]}))
    assert cp.low == (0.0,) and cp.names == ("phi",)
    for change, match in (({"names": ()}, "at least one"),
                          ({"high": (1.0, 2.0)}, "entries"),
                          ({"high": (0.0,)}, "low < high"),
                          ({"low": (-np.inf,)}, "low < high"),
                          ({"line": None}, "callable")):
        with pytest.raises(ValueError, match=match):
            CostateParametrisation(**(good | change))
    theta, omega, u = sympy.symbols("theta omega u")
    bad_line = CostateParametrisation(**(good | {"line": lambda x, p: ((0,), (1,), 1)}))
    with pytest.raises(ValueError, match="2 entries"):
        build_system("bad", [theta, omega], [u], [omega, sympy.sin(theta)], [[0], [1]],
                     state_low=[-1, -1], state_high=[1, 1], costate_parametrisation=bad_line)


# --------------------------------------------------------------------------- double integrator


def test_oracle_closed_form():
    rng = np.random.default_rng(1)
    x0, x1 = rng.uniform(-2, 2, (60, 2)), rng.uniform(-2, 2, (60, 2))
    grid = np.geomspace(1e-4, 30.0, 20001)
    for w in (1.0, 0.3):
        t_opt, c_opt = optimal_arrival(x0, x1, w)
        np.testing.assert_allclose(cost_for_duration(x0, x1, t_opt, w), c_opt, rtol=1e-12)
        for i in range(len(x0)):
            c = cost_for_duration(np.broadcast_to(x0[i], (len(grid), 2)),
                                  np.broadcast_to(x1[i], (len(grid), 2)), grid, w)
            assert c_opt[i] <= c.min() * (1 + 1e-12)  # global over T ...
            assert c_opt[i] >= c.min() * (1 - 1e-5)  # ... and the grid gets close to it
    # the Gramian form agrees with the expanded one
    t = 0.8
    d = x1[0] - np.array([x0[0, 0] + x0[0, 1] * t, x0[0, 1]])
    gram = np.array([[t**3 / 3, t**2 / 2], [t**2 / 2, t]])
    np.testing.assert_allclose(cost_for_duration(x0[:1], x1[:1], t, 1.0),
                               t + 0.5 * d @ np.linalg.solve(gram, d), rtol=1e-12)
    t_opt, c_opt = optimal_arrival([[0, 0], [1, 1], [np.nan, 0]], [[0, 0], [1, 1], [0, 0]], 1.0)
    np.testing.assert_allclose(t_opt[:2], [0.0, np.sqrt(6.0)])  # return with v = 1: T^2 = 6
    np.testing.assert_allclose(c_opt[:2], [0.0, 2.0 * np.sqrt(6.0)])
    assert np.isnan(t_opt[2]) and np.isnan(c_opt[2])


@pytest.mark.parametrize("w", [1.0, 0.3])
def test_indirect_method_matches_oracle(double_integrator, w):
    """Extremals with H* = 0 (rolled out by rollout_jit) against the closed-form cost.

    For the fixed duration t the extremal is the unique optimum (linear-quadratic), so its
    integrated cost equals c(t) everywhere; H* = 0 makes t a stationary point of c, and for
    short segments the global minimiser, where the oracle equals the integrated cost.
    """
    di, rng = double_integrator, np.random.default_rng(2)
    n_traj, dt, steps = 200, 0.01, 200
    x0 = rng.uniform(di.state_low, di.state_high, (n_traj, 2))
    p = rng.uniform(di.param_low, di.param_high, (n_traj, 2))
    lam, valid = di.costate_from_params(x0, p, w)
    assert valid.all()
    trajs = np.stack([di.rollout_jit(np.r_[x0[i], lam[i], 0.0], w, dt, steps)
                      for i in range(n_traj)])
    t = dt * np.arange(1, steps + 1)
    start = np.repeat(x0, steps, axis=0)
    end = trajs[:, 1:, :2].reshape(-1, 2)
    integrated = trajs[:, 1:, 4].reshape(-1)
    durations = np.tile(t, n_traj)
    # RK4 is exact for this polynomial flow: only rounding (mostly in c(t) at small t)
    np.testing.assert_allclose(cost_for_duration(start, end, durations, w), integrated,
                               rtol=1e-8)
    oracle = optimal_cost(start, end, w).reshape(n_traj, steps)
    integrated = integrated.reshape(n_traj, steps)
    assert np.all(oracle <= integrated * (1 + 1e-8))  # the oracle is a global minimum
    # moderate costates: the extremal stays globally optimal for at least 0.5 s (w >= 0.3)
    moderate = np.abs(lam).max(axis=1) <= 5.0
    assert moderate.mean() > 0.6
    short = t <= 0.5
    rel = (integrated - oracle) / integrated
    assert np.max(rel[np.ix_(moderate, short)]) < 1e-8
    # overall, most short segments are globally optimal; violent ones (huge costates) are not
    assert np.mean(rel[:, short] < 1e-8) > 0.85


# --------------------------------------------------------------------------- code generation


def test_generated_modules_are_cached(cache_dir, dir_pendulum, cold_stats):
    sym_pendulum = dir_pendulum
    path = Path(sys.modules[sym_pendulum.rhs.py_func.__module__].__file__)
    assert path.parent == cache_dir / "systems"
    assert path.name == f"rrtcolearn_sys_{hashlib.sha256(path.read_bytes()).hexdigest()}.py"
    stat = path.stat()
    again = direction_pendulum()  # same process: the module is reused
    assert again.rhs is sym_pendulum.rhs
    # as a new process would: import again from the file and numba's on-disk cache
    del sys.modules[path.stem]
    fresh = direction_pendulum()
    assert fresh.rhs is not sym_pendulum.rhs
    loaded = warm_up(fresh)
    new = path.stat()
    assert (new.st_mtime_ns, new.st_ino) == (stat.st_mtime_ns, stat.st_ino)  # not rewritten
    # the first build compiled every kernel (a miss each, in a fresh cache); the fresh import
    # loads every one from numba's cache (a hit each) and compiles none
    assert cold_stats["pendulum_direction"] == dict.fromkeys(KERNELS, (0, 1))
    assert loaded == dict.fromkeys(KERNELS, (1, 0))
    # names are not part of the code; another definition gets another file
    renamed = direction_pendulum(state_names=("th", "om"))
    assert renamed.rhs is fresh.rhs
    files = set((cache_dir / "systems").glob("rrtcolearn_sys_*.py"))
    theta, omega, u = sympy.symbols("theta omega u")
    damped = build_system("damped", [theta, omega], [u],
                          [omega, sympy.sin(theta) - 0.1 * omega], [[0], [1]],
                          state_low=[-1, -1], state_high=[1, 1])
    assert damped.source != sym_pendulum.source
    assert len(set((cache_dir / "systems").glob("rrtcolearn_sys_*.py")) - files) == 1
    # a corrupted file is rewritten
    path.write_text("corrupted")
    del sys.modules[path.stem]
    repaired = direction_pendulum()
    assert path.read_text() == repaired.source == sym_pendulum.source


@pytest.mark.parametrize("which", ["double_integrator", "pendulum"])
def test_symbolic_system_pickles_for_spawned_workers(which, cache_dir):
    """Spawned workers (parallel.py) rebuild the generated module from the pickled source; the
    pendulum's own costate functions travel by reference."""
    from rrtcolearn.integrate import rollout
    from rrtcolearn.parallel import ExecutionSettings, map_tasks

    system = make(which)
    again = pickle.loads(pickle.dumps(system))
    for name in ("rhs", "rollout_jit", "rollout_batch_jit", "costate_from_params",
                 "costate_from_params_jit", "optimal_control", "hamiltonian", "dynamics"):
        assert getattr(again, name) is getattr(system, name), name
    assert again.param_names == system.param_names
    rng = np.random.default_rng(3)
    x0 = rng.uniform(system.state_low, system.state_high, (20, 2))
    p = rng.uniform(system.param_low, system.param_high, (20, system.n_params))
    lam, valid = system.costate_from_params(x0, p, 1.0)
    out = np.empty(2)
    for i in range(20):
        assert again.costate_from_params_jit(x0[i], p[i], 1.0, out) == valid[i]
    tasks = [np.r_[x0[i], lam[i], 0.0] for i in np.flatnonzero(valid)[:2]]
    # also after the generated module was imported anew (as from another cache directory)
    del sys.modules[system.rhs.py_func.__module__]
    assert make(which).rhs is not system.rhs
    fn = functools.partial(rollout, system, w=1.0, dt=0.01, n_steps=50)
    spawned = map_tasks(fn, tasks, ExecutionSettings("processes", 1))
    for z0, traj in zip(tasks, spawned, strict=True):
        np.testing.assert_array_equal(traj, fn(z0))
