"""System registry: ``make(name)``, ``register(name, factory)``, ``list_systems()``."""

from __future__ import annotations

from collections.abc import Callable

from rrtcolearn.systems.base import System
from rrtcolearn.systems.pendulum import make_pendulum

_REGISTRY: dict[str, Callable[[], System]] = {}
_CONFIGS: dict[str, dict] = {}


def register(name: str, factory: Callable[[], System], config: dict | None = None) -> None:
    """Make ``factory`` available as ``make(name)``; ``config`` is the system's recommended
    configuration (nested dict), applied under the user's (see `recommended_config`)."""
    _REGISTRY[name] = factory
    _CONFIGS[name] = dict(config or {})


def recommended_config(name: str) -> dict:
    """The recommended configuration of system ``name``: the registry's, or for a
    ``module:attribute`` system its ``defaults["config"]``; {} when there is none (or the
    system cannot be built: the error is reported where it is built)."""
    if name in _REGISTRY:
        return _CONFIGS[name]
    try:
        return dict(make(name).defaults.get("config", {}))
    except Exception:  # reported with its reason by the step that builds the system
        return {}


def list_systems() -> list[str]:
    """Names of the registered systems."""
    return sorted(_REGISTRY)


def make(name: str) -> System:
    """Build the system ``name``: a registered name, or ``module:attribute`` naming a
    `System` or a function returning one in the user's own Python module (imported, with the
    current directory on the path). ValueError with a one-line reason otherwise."""
    if name not in _REGISTRY and ":" in name:
        return _from_module(name)
    try:
        factory = _REGISTRY[name]
    except KeyError:
        known = ", ".join(list_systems())
        raise ValueError(f"unknown system {name!r}; known systems: {known}, or give "
                         "module:attribute") from None
    return factory()


def _from_module(spec: str) -> System:
    import importlib
    import os
    import sys

    module_name, _, attribute = spec.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"system {spec!r}: expected module:attribute")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"system {spec!r}: cannot import {module_name!r} ({exc})") from None
    try:
        obj = getattr(module, attribute)
    except AttributeError:
        raise ValueError(f"system {spec!r}: {module_name!r} has no {attribute!r}") from None
    system = obj() if callable(obj) and not isinstance(obj, System) else obj
    if not isinstance(system, System):
        raise ValueError(f"system {spec!r} is a {type(system).__name__}, not a System")
    return system


def _double_integrator() -> System:
    # imported on use: the symbolic derivation needs sympy, which takes a while to import
    from rrtcolearn.systems.double_integrator import make_double_integrator

    return make_double_integrator()


def _cartpole() -> System:
    from rrtcolearn.systems.cartpole import make_cartpole

    return make_cartpole()


def _acrobot() -> System:
    from rrtcolearn.systems.acrobot import make_acrobot

    return make_acrobot()


def _quadrotor() -> System:
    from rrtcolearn.systems.quadrotor import make_quadrotor

    return make_quadrotor()


# Recommended configurations: the pendulum's are the package defaults (the paper's); the
# others were chosen by measurement (README "Other systems", bench/systems_bench.py).
_HIGHER_DIMENSIONAL_PLAN = {
    # steering parameters are costate directions in [-1, 1]: the pendulum's sigmas (pi/4 and
    # pi/2 on a 2*pi range) scaled to that range would be 0.25 and 0.5
    "sigma": 0.25, "sigma_goal": 0.5,
    "control_samples": 16, "max_candidates": 8, "extend_distance": 0.5,
    "goal_tolerance": 0.3, "wrap_goal": True, "time_limit": 60.0,
}
register("pendulum", make_pendulum)
register("double_integrator", _double_integrator, {
    "name": "double-integrator",
    "generate": {"n_simulations": 100_000},
})
register("cartpole", _cartpole, {
    "name": "cartpole-swingup",
    "generate": {"n_simulations": 100_000, "max_cost": 50.0},
    "learn": {"validity_threshold": 2.0, "learner": "mlp"},
    # the last edge by shooting, tried from nodes within weighted distance 2 of the goal:
    # 50 of 50 seeded swing-ups within 60 s (49 of 50 within the data's reach of 1.5; README)
    "plan": {**_HIGHER_DIMENSIONAL_PLAN, "goal_connect": True, "connect_reach": 2.0},
})
register("acrobot", _acrobot, {
    "name": "acrobot-swingup",
    "generate": {"n_simulations": 100_000, "max_cost": 50.0},
    "learn": {"validity_threshold": 2.0, "learner": "mlp"},
    # shooting from U's guess gives no edge into the upright (the boundary value problem is
    # ill-conditioned there); continuation along extremals from the goal does: 50 of 50
    # seeded swing-ups within 60 s (60 000 extremals, their states at least 1 s from the
    # goal kept; README)
    "plan": {**_HIGHER_DIMENSIONAL_PLAN, "goal_funnel": 60_000, "funnel_min_duration": 1.0},
})
register("quadrotor", _quadrotor)

__all__ = ["System", "list_systems", "make", "recommended_config", "register"]
