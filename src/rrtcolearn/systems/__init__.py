"""System registry: ``make(name)``, ``register(name, factory)``, ``list_systems()``."""

from __future__ import annotations

from collections.abc import Callable

from rrtcolearn.systems.base import System
from rrtcolearn.systems.pendulum import make_pendulum

_REGISTRY: dict[str, Callable[[], System]] = {}
_CONFIGS: dict[str, dict | None] = {}


def register(name: str, factory: Callable[[], System], config: dict | None = None) -> None:
    """Make ``factory`` available as ``make(name)``; ``config`` is the system's recommended
    configuration (nested dict), applied under the user's (see `recommended_config`); without
    it, the system's own ``defaults["config"]``, as for a ``module:attribute`` name."""
    _REGISTRY[name] = factory
    _CONFIGS[name] = None if config is None else dict(config)


def recommended_config(name: str) -> dict:
    """The recommended configuration of system ``name``: the one it was registered with,
    else (a registered name without one, read once, or a ``module:attribute`` system) its
    ``defaults["config"]``; {} when there is none (or the system cannot be built: the error
    is reported where it is built)."""
    if name in _REGISTRY and _CONFIGS[name] is not None:
        return _CONFIGS[name]
    try:
        config = dict(make(name).defaults.get("config", {}))
    except Exception:  # reported with its reason by the step that builds the system
        return {}
    if name in _REGISTRY:
        _CONFIGS[name] = config
    return config


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
    if factory in _OWN_DEFINITIONS:
        # rebuilt from its build record when one matches: no sympy (build_record)
        from rrtcolearn.systems.build_record import build

        return build(factory)
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
        # the module itself not found (not an import inside it): say where it is looked for
        where = ("; it is looked for in the current directory and on PYTHONPATH: run from "
                 "the directory that holds it or add that directory to PYTHONPATH"
                 if isinstance(exc, ModuleNotFoundError) and exc.name is not None
                 and f"{module_name}.".startswith(f"{exc.name}.") else "")
        raise ValueError(f"system {spec!r}: cannot import {module_name!r} ({exc}){where}"
                         ) from None
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


# What a user would state about these systems' standard queries (their goal regions and
# time limits); every learner and planner setting is derived (rrtcolearn.derive).
_SWING_UP = {"goal_tolerance": 0.3, "wrap_goal": True, "time_limit": 60.0}
register("pendulum", make_pendulum, {})
register("double_integrator", _double_integrator, {"name": "double-integrator"})
register("cartpole", _cartpole, {"name": "cartpole-swingup", "plan": _SWING_UP})
register("acrobot", _acrobot, {"name": "acrobot-swingup", "plan": _SWING_UP})
register("quadrotor", _quadrotor)
# the package's own sympy definitions: their builds are recorded (`build_record`)
_OWN_DEFINITIONS = (make_pendulum, _double_integrator, _cartpole, _acrobot, _quadrotor)

__all__ = ["System", "list_systems", "make", "recommended_config", "register"]
