"""System registry: ``make(name)``, ``register(name, factory)``, ``list_systems()``."""

from __future__ import annotations

from collections.abc import Callable

from rrtcolearn.systems.base import System
from rrtcolearn.systems.pendulum import make_pendulum

_REGISTRY: dict[str, Callable[[], System]] = {}


def register(name: str, factory: Callable[[], System]) -> None:
    """Make ``factory`` available as ``make(name)``."""
    _REGISTRY[name] = factory


def list_systems() -> list[str]:
    """Names of the registered systems."""
    return sorted(_REGISTRY)


def make(name: str) -> System:
    """Build the registered system ``name``; ValueError names the known ones otherwise."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        known = ", ".join(list_systems())
        raise ValueError(f"unknown system {name!r}; known systems: {known}") from None
    return factory()


def _double_integrator() -> System:
    # imported on use: the symbolic derivation needs sympy, which takes a while to import
    from rrtcolearn.systems.double_integrator import make_double_integrator

    return make_double_integrator()


register("pendulum", make_pendulum)
register("double_integrator", _double_integrator)

__all__ = ["System", "list_systems", "make", "register"]
