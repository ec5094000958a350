"""Build a `System` from a sympy definition of an input-affine system.

The user gives ``x' = a(x) + B(x) u`` with running cost ``w + u^T R u / 2`` (``R`` constant,
symmetric positive definite) as sympy expressions in the state symbols, physical parameters
already numbers (or substituted through ``parameters``). Pontryagin's machinery is derived
symbolically:

    H   = w + u^T R u / 2 + lambda^T (a + B u),
    u*  = -R^{-1} B^T lambda,
    H*  = w + lambda^T a - lambda^T M lambda / 2,   M = B R^{-1} B^T,
    x'  = dH*/dlambda,   lambda' = -dH*/dx,   cost' = w + lambda^T M lambda / 2.

Code generation (`rrtcolearn.systems.codegen`; the derivation: `rrtcolearn.systems.derivation`):
sympy's code printers (after ``sympy.cse``) write the scalar kernels
``rhs(z, w, out)``, ``input_max_abs(z)`` and ``costate_from_params_jit`` (numba, cached) and the
vectorised numpy functions into one module file in the cache directory, named by the SHA-256 of
its text, so different definitions never collide and an unchanged definition reuses both the
file and numba's on-disk cache (numba needs a real file to cache; see ``integrate``). Only the
printers produce the generated text: no user string is ever evaluated or pasted into it.

Costate parametrisation (steering parameters): the costate direction ``d`` given by its ``n``
components, ``param_low = -1``, ``param_high = 1``, none circular. ``costate_from_params``
normalises ``d`` and scales it onto H* = 0: along ``lambda = s d``,
``H*(s d) = w + s p - s^2 q / 2`` with ``p = d^T a(x)`` and ``q = d^T M(x) d >= 0``. For
``q > 0`` (and ``w > 0``) the roots have opposite signs, so the positive root
``s = (p + sqrt(p^2 + 2 q w)) / q = 2 w / (sqrt(p^2 + 2 q w) - p)`` is unique; for ``q = 0``
``s = -w / p`` exists only when ``p < 0``. Every H* = 0 costate thus comes from exactly one unit
direction. Components rather than hyperspherical angles because they are continuous on the whole
sphere (no poles, no wrap-around), so a k-NN learner can average neighbouring parameters and
``costate_from_params`` renormalises the average (only an exactly opposite pair cancels).
Uniform sampling of the box gives directions that are denser towards the box corners; every
direction is still reachable.

A system author may replace the direction by their own parametrisation: a
`CostateParametrisation` (parameter names, sampling box, which are circular, a vectorised numpy
``from_params(x, p, w) -> (lambda, valid)`` and a scalar ``numba.njit(cache=True)``
``from_params_jit(x, p, w, out) -> bool``, both module-level functions of the author's module so
they pickle by reference), e.g. the pendulum's angle phi (`rrtcolearn.systems.pendulum`). The
generated module does not depend on the parametrisation; only the `System`'s fields do.

Cache directory: ``$RRTCOLEARN_CACHE/systems`` if that variable is set, else
``$XDG_CACHE_HOME/rrtcolearn/systems`` or ``~/.cache/rrtcolearn/systems``. Writing, importing
and wrapping the generated modules needs no sympy and lives in
`rrtcolearn.systems.generated`, which this module re-exports.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy

from rrtcolearn.systems.base import System
from rrtcolearn.systems.codegen import generate_source
from rrtcolearn.systems.derivation import Derivation, derive, limit_derivation
from rrtcolearn.systems.generated import (
    SymbolicSystem,
    direction_from_costate,
    generated_dir,
    load_generated_module,
)

__all__ = [
    "CostateParametrisation",
    "Derivation",
    "SymbolicSystem",
    "build_system",
    "derive",
    "generate_source",
    "generated_dir",
    "invariant_coordinates",
    "limit_derivation",
    "load_generated_module",
    "planar_rotation",
    "with_input_limits",
]


# --------------------------------------------------------------------------- System


@dataclass(frozen=True)
class CostateParametrisation:
    """A system author's costate parametrisation: a line in costate space per parameter vector.

    names, low, high : the k steering parameters and their sampling box (low < high, finite).
    circular : which parameters live on a circle of period ``high - low``.
    line : ``line(x, p) -> (lambda0, e, right)`` called once at build time with the state and
        parameter symbols (sympy), returning sympy expressions: the costates of parameters p
        are ``lambda0 + t e`` with t the root of H*(x, lambda0 + t e) = 0 that lies on the
        right (the larger root, where ``right >= 0``) or on the left. H* along a line is
        concave (piecewise quadratic with input limits), so each side has at most one root and
        the library solves it exactly, with or without limits.
    inverse : optional ``inverse(x, lam, xdot) -> k expressions`` (sympy, in the state,
        costate and state-derivative-under-u* symbols), the parameters of a costate on
        H* = 0; ``xdot . e`` is <= 0 at a right root and >= 0 at a left one (it is the slope of
        H* along the line), which is how an inverse tells the sides apart. Needed for data
        simulated backwards from a goal (`System.params_from_costate`).

    ``line`` and ``inverse`` should be module-level functions of an importable module, so
    that the system pickles (by reference) for spawned workers.
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    circular: tuple[bool, ...]
    line: Callable
    inverse: Callable | None = None

    def __post_init__(self) -> None:
        names = tuple(str(v) for v in self.names)
        low = tuple(float(v) for v in np.ravel(self.low))
        high = tuple(float(v) for v in np.ravel(self.high))
        circular = tuple(bool(v) for v in self.circular)
        k = len(names)
        if k == 0 or len(set(names)) != k:
            raise ValueError("a costate parametrisation needs at least one parameter name, "
                             f"all distinct, got {names}")
        if not len(low) == len(high) == len(circular) == k:
            raise ValueError(f"low, high and circular need {k} entries (one per parameter)")
        lo, hi = np.array(low), np.array(high)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise ValueError("the parameter box needs finite bounds with low < high")
        if not callable(self.line) or not (self.inverse is None or callable(self.inverse)):
            raise ValueError("line (and inverse, if given) must be callable")
        for name, value in (("names", names), ("low", low), ("high", high),
                            ("circular", circular)):
            object.__setattr__(self, name, value)

    def expressions(self, der: Derivation) -> tuple:
        """``(p, lambda0, e, right, inverse)`` in the derivation's symbols, checked."""
        n = der.n
        ps = tuple(sympy.Symbol(f"p{i}", real=True) for i in range(len(self.names)))
        vs = tuple(sympy.Symbol(f"v{i}", real=True) for i in range(n))
        lam0, e, right = self.line(der.x, ps)
        lam0 = [sympy.sympify(v) for v in lam0]
        e = [sympy.sympify(v) for v in e]
        right = sympy.sympify(right)
        if len(lam0) != n or len(e) != n:
            raise ValueError(f"line must give lambda0 and e with {n} entries each")
        allowed = set(der.x) | set(ps)
        for ex in (*lam0, *e, right):
            if not ex.free_symbols <= allowed:
                raise ValueError("line may use the state and parameter symbols only, found "
                                 f"{sorted(map(str, ex.free_symbols - allowed))}")
        inverse = None
        if self.inverse is not None:
            inverse = [sympy.sympify(v) for v in self.inverse(der.x, der.lam, vs)]
            if len(inverse) != len(ps):
                raise ValueError(f"inverse must give {len(ps)} expressions (one per parameter)")
            allowed = set(der.x) | set(der.lam) | set(vs)
            for ex in inverse:
                if not ex.free_symbols <= allowed:
                    raise ValueError("inverse may use the state, costate and state-derivative "
                                     f"symbols only, found "
                                     f"{sorted(map(str, ex.free_symbols - allowed))}")
        return ps, lam0, e, right, inverse


def invariant_coordinates(der: Derivation, line: tuple | None = None) -> tuple[int, ...]:
    """The state indices i whose symbol x_i appears in none of the expressions the optimal
    control problem is made of: a(x), B(x), H*, the state+costate ODEs, u*, the running cost,
    the costate ray's terms, and ``line`` (a costate parametrisation's expressions,
    `CostateParametrisation.expressions`).

    Then a trajectory from x0 + c e_i under the same steering parameters is the one from x0
    shifted by c e_i, with the same cost and duration: J and U are invariant to shifting x0
    and x1 together along e_i. An angle coordinate qualifies too when nothing depends on it
    (its wrap is then a shift like any other). The test is syntactic, so it is conservative:
    an expression that depends on x_i only in a form sympy does not cancel (sin^2 + cos^2)
    hides an invariance, never invents one.
    """
    exprs = [*der.drift, *der.input_matrix, der.h_star, *der.state_ode, *der.costate_ode,
             *der.optimal_control, der.running_cost, der.ray_slope, *der.ray_factors]
    if line is not None:
        _, lam0, direction, right, inverse = line
        exprs += [*lam0, *direction, right, *(inverse or ())]
    used = set().union(*(sympy.sympify(e).free_symbols for e in exprs))
    return tuple(i for i, xi in enumerate(der.x) if xi not in used)


def planar_rotation(der: Derivation, invariant: Sequence[int],
                    line: tuple | None = None) -> tuple[int, ...]:
    """``(i, j, k)`` when the system is equivariant under rotating the plane of the invariant
    coordinates (x_i, x_j) by any angle phi while adding phi to x_k (the heading); () when no
    such triple exists or the costates are parametrised by the author (``line``).

    The test is exact: with the rotated state g x = (R(phi) (x_i, x_j), x_k + phi, rest),
    sympy must simplify a(g x) - T a(x) and every column of B(g x) - T B(x) to zero for a
    symbolic phi, T rotating the (i, j) components of a vector field and keeping the others
    (the tangent map of g). R (the input weight) is constant and u is untouched, so g maps
    solutions to solutions with the same inputs, cost and duration, and the costate to
    T lambda (T is orthogonal). The default costate parametrisation (the direction d,
    normalised onto H* = 0) then maps d to T d: p = d^T a and q = d^T M d are unchanged.
    An author's parametrisation may transform any other way, so it is not used. Only
    invariant coordinates are candidates for (i, j): the learners' body frame needs the
    translations as well (`rrtcolearn.learn.features`). The first (i, j, k) found in index
    order is returned (rotating (x_j, x_i) is the inverse rotation: one order fits).
    """
    if line is not None:
        return ()
    phi = sympy.Symbol("phi", real=True)
    c, s = sympy.cos(phi), sympy.sin(phi)
    fields = [list(der.drift)] + [list(der.input_matrix[:, col])
                                  for col in range(der.input_matrix.shape[1])]
    x = der.x
    rng = np.random.default_rng(0)
    probe = {xi: float(v) for xi, v in zip(x, rng.uniform(-2.0, 2.0, len(x)), strict=True)}
    probe[phi] = 0.7317

    def differences(i: int, j: int, k: int) -> list:
        g = {x[i]: c * x[i] - s * x[j], x[j]: s * x[i] + c * x[j], x[k]: x[k] + phi}
        out = []
        for f in fields:
            moved = [sympy.sympify(e).subs(g, simultaneous=True) for e in f]
            turned = list(f)
            turned[i], turned[j] = c * f[i] - s * f[j], s * f[i] + c * f[j]
            out += [m - t for m, t in zip(moved, turned, strict=True)]
        return out

    for i in invariant:
        for j in invariant:
            if i == j:
                continue
            for k in range(der.n):
                if k in (i, j):
                    continue
                diffs = differences(i, j, k)
                # a numeric probe first (cheap, rejects almost every candidate), then
                # the exact check that decides
                if any(abs(complex(d.evalf(subs=probe))) > 1e-9 for d in diffs):
                    continue
                if all(sympy.simplify(sympy.expand(sympy.expand_trig(d))) == 0
                       for d in diffs):
                    return (int(i), int(j), int(k))
    return ()


def _generated_fields(der: Derivation, cp: CostateParametrisation | None,
                      cache_dir: str | os.PathLike | None) -> dict:
    """The `System` fields that come from the generated module of ``der`` (and ``cp``)."""
    n = der.n
    line = None if cp is None else cp.expressions(der)
    source = generate_source(der, line)
    module = load_generated_module(source, cache_dir)
    invariant = invariant_coordinates(der, line)
    if cp is None:
        params = dict(param_names=None, param_low=-np.ones(n), param_high=np.ones(n),
                      param_circular=(False,) * n, params_from_costate=direction_from_costate)
    else:
        params = dict(param_names=cp.names, param_low=np.array(cp.low),
                      param_high=np.array(cp.high), param_circular=cp.circular,
                      params_from_costate=getattr(module, "params_from_costate", None))
    return dict(
        **params,
        costate_from_params=module.costate_from_params,
        costate_from_params_jit=module.costate_from_params_jit,
        rhs=module.rhs,
        rollout_jit=module.rollout_jit,
        rollout_batch_jit=module.rollout_batch_jit,
        input_max_abs_jit=module.input_max_abs,
        optimal_control=module.optimal_control,
        hamiltonian=module.hamiltonian,
        dynamics=module.dynamics,
        propagate_jit=module.propagate_jit,
        closed_loop_jit=module.closed_loop_jit,
        rollout_draws_jit=module.rollout_draws_jit,
        hold_jit=module.hold_jit,
        explore_jit=module.explore_jit,
        input_low=np.array(der.input_low),
        input_high=np.array(der.input_high),
        invariant_coordinates=invariant,
        planar_rotation=planar_rotation(der, invariant, line),
        source=source,
        derivation=der,
    )


def build_system(
    name: str,
    states: Sequence[sympy.Symbol],
    inputs: Sequence[sympy.Symbol],
    drift: Any,
    input_matrix: Any,
    input_weight: Any = None,
    *,
    state_low: Sequence[float],
    state_high: Sequence[float],
    angle_dims: Sequence[int] = (),
    parameters: Mapping[sympy.Symbol, float] | None = None,
    input_low: Sequence[float] | float | None = None,
    input_high: Sequence[float] | float | None = None,
    state_names: Sequence[str] | None = None,
    input_names: Sequence[str] | None = None,
    description: str = "",
    defaults: dict | None = None,
    cache_dir: str | os.PathLike | None = None,
    costate_parametrisation: CostateParametrisation | None = None,
) -> SymbolicSystem:
    """Derive, generate, compile (lazily, cached) and wrap a system ``x' = a(x) + B(x) u``.

    ``drift`` = a(x) (n), ``input_matrix`` = B(x) (n x m), ``input_weight`` = R (m x m,
    identity by default); ``input_low``/``input_high`` bound the inputs (scalar or one per
    input; None: unbounded), and the optimal control then saturates (`limit_derivation`);
    ``state_low``/``state_high`` is the start-state sampling box and
    ``angle_dims`` the coordinates with period 2*pi (the definition must be periodic in them).
    Names default to the symbols' names. The steering parameters are the costate direction's
    components ``d_<state>`` in [-1, 1] unless ``costate_parametrisation`` gives the author's
    own (module docstring).
    """
    der = derive(states, inputs, drift, input_matrix, input_weight, parameters,
                 input_low, input_high)
    n, m = der.n, der.m
    low = np.asarray(state_low, dtype=float)
    high = np.asarray(state_high, dtype=float)
    if low.shape != (n,) or high.shape != (n,):
        raise ValueError(f"state_low and state_high need {n} entries")
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
        raise ValueError("the state box needs finite bounds with state_low < state_high")
    angles = tuple(int(j) for j in angle_dims)
    if len(set(angles)) != len(angles) or any(not 0 <= j < n for j in angles):
        raise ValueError(f"angle_dims must be distinct state indices in [0, {n}), got {angles}")
    s_names = tuple(state_names) if state_names is not None else tuple(map(str, states))
    i_names = tuple(input_names) if input_names is not None else tuple(map(str, inputs))
    if len(s_names) != n or len(i_names) != m:
        raise ValueError("state_names / input_names do not match the numbers of symbols")
    if costate_parametrisation is not None and not der.input_weight.is_diagonal():
        raise ValueError("a costate parametrisation needs a diagonal R")
    gen = _generated_fields(der, costate_parametrisation, cache_dir)
    if gen["param_names"] is None:
        gen["param_names"] = tuple(f"d_{s}" for s in s_names)
    return SymbolicSystem(
        name=name,
        state_names=s_names,
        input_names=i_names,
        state_low=low,
        state_high=high,
        angle_dims=angles,
        description=description,
        defaults=dict(defaults or {}),
        parametrisation=costate_parametrisation,
        **gen,
    )


def with_input_limits(system: System, input_low: Sequence[float] | float | None,
                      input_high: Sequence[float] | float | None,
                      cache_dir: str | os.PathLike | None = None) -> System:
    """The same system with its inputs confined to ``[input_low, input_high]`` (replacing any
    limits it had; None, None removes them): the optimal control saturates and the costate
    sampler solves the saturated H* = 0 (`limit_derivation`). Only systems built by
    `build_system` can be re-derived; ValueError otherwise."""
    current, parametrisation = system.symbolic() if isinstance(system, SymbolicSystem) \
        else (None, None)
    if current is None:
        raise ValueError(f"system {system.name!r} was not built by build_system: its input "
                         "limits cannot be changed (give them to build_system)")
    der = limit_derivation(current, input_low, input_high)
    if der.input_low == current.input_low and der.input_high == current.input_high:
        return system
    gen = _generated_fields(der, parametrisation, cache_dir)
    gen.pop("param_names")
    # the sampling box of the parameters may have been overridden: keep it
    for key in ("param_low", "param_high"):
        gen.pop(key)
    return dataclasses.replace(system, **gen, parametrisation=parametrisation)
