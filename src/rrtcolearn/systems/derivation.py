"""Pontryagin's conditions of an input-affine system, derived symbolically (sympy).

``x' = a(x) + B(x) u`` with running cost ``w + u^T R u / 2``: the Hamiltonian, the optimal
input (clipped into an input box where the system has one), H*, the state + costate
right-hand side and the cost rate, in internal symbols; `rrtcolearn.systems.codegen` writes
them as code and `rrtcolearn.systems.symbolic.build_system` makes the `System`
(the method in full: that module's docstring).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy


@dataclass(frozen=True)
class Derivation:
    """The Pontryagin quantities of one definition, in internal symbols.

    States are ``x0..``, costates ``l0..``, inputs ``u0..``, direction components ``d0..`` and
    the time weight ``w`` (all real), so the generated code never depends on user names.
    """

    x: tuple[sympy.Symbol, ...]
    lam: tuple[sympy.Symbol, ...]
    u: tuple[sympy.Symbol, ...]
    d: tuple[sympy.Symbol, ...]
    w: sympy.Symbol
    drift: sympy.Matrix  # a(x), (n, 1)
    input_matrix: sympy.Matrix  # B(x), (n, m)
    input_weight: sympy.Matrix  # R, (m, m)
    hamiltonian: sympy.Expr  # H(x, lambda, u)
    optimal_control: sympy.Matrix  # -R^{-1} B^T lambda, (m, 1); clipped to the limits in code
    h_star: sympy.Expr  # H*(x, lambda)
    state_ode: tuple[sympy.Expr, ...]  # dH*/dlambda
    costate_ode: tuple[sympy.Expr, ...]  # -dH*/dx
    running_cost: sympy.Expr  # w + u*^T R u* / 2
    ray_slope: sympy.Expr  # p = d^T a(x)
    ray_factors: tuple[sympy.Expr, ...]  # g = L^{-1} B^T d with R = L L^T, so q = |g|^2
    input_low: tuple[float, ...] = ()  # per-input box, -inf/inf where unbounded
    input_high: tuple[float, ...] = ()

    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def m(self) -> int:
        return len(self.u)

    @property
    def saturated(self) -> bool:
        """Whether any input has a finite limit (u* is then the clipped free control)."""
        return any(np.isfinite(self.input_low)) or any(np.isfinite(self.input_high))


def _as_matrix(value: Any, shape: tuple[int, int], what: str) -> sympy.Matrix:
    mat = sympy.Matrix(value)
    if mat.shape != shape and mat.shape == shape[::-1] and 1 in shape:
        mat = mat.T
    if mat.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {mat.shape}")
    return mat


def derive(
    states: Sequence[sympy.Symbol],
    inputs: Sequence[sympy.Symbol],
    drift: Any,
    input_matrix: Any,
    input_weight: Any = None,
    parameters: Mapping[sympy.Symbol, float] | None = None,
    input_low: Sequence[float] | float | None = None,
    input_high: Sequence[float] | float | None = None,
) -> Derivation:
    """Validate a definition and derive u*, H*, the state+costate ODEs and the ray terms.

    ``drift`` is a(x) (n entries), ``input_matrix`` B(x) (n x m), ``input_weight`` R (m x m,
    identity when None); ``parameters`` maps remaining symbols to numbers; ``input_low`` /
    ``input_high`` bound each input (scalar or m values, +-inf or None for none; see
    `limit_derivation`). ValueError explains a malformed definition (wrong shapes, unknown
    symbols, inputs inside a or B, R not constant symmetric positive definite, limits with a
    non-diagonal R).
    """
    states, inputs = tuple(states), tuple(inputs)
    n, m = len(states), len(inputs)
    if n == 0 or m == 0:
        raise ValueError("a system needs at least one state and one input")
    for s in (*states, *inputs):
        if not isinstance(s, sympy.Symbol):
            raise ValueError(f"states and inputs must be sympy Symbols, got {s!r}")
    if len(set(states + inputs)) != n + m:
        raise ValueError("state and input symbols must be distinct")
    a = _as_matrix(drift, (n, 1), "drift a(x)")
    b = _as_matrix(input_matrix, (n, m), "input matrix B(x)")
    r = sympy.eye(m) if input_weight is None else _as_matrix(input_weight, (m, m), "R")
    if parameters:
        subs = {sympy.sympify(k): sympy.sympify(v) for k, v in parameters.items()}
        a, b, r = a.xreplace(subs), b.xreplace(subs), r.xreplace(subs)
    input_set = set(inputs)
    for mat, what in ((a, "drift a(x)"), (b, "input matrix B(x)")):
        free = mat.free_symbols
        if free & input_set:
            raise ValueError(f"{what} must not depend on the inputs (the form is a(x) + B(x) u),"
                             f" found {sorted(map(str, free & input_set))}")
        unknown = free - set(states)
        if unknown:
            raise ValueError(f"{what} has symbols that are not states: "
                             f"{sorted(map(str, unknown))}; substitute them via `parameters`")
    if r.free_symbols:
        raise ValueError(f"R must be constant, has symbols {sorted(map(str, r.free_symbols))}")
    r_num = np.array(r.evalf(), dtype=float)
    if not np.all(np.isfinite(r_num)) or not np.allclose(r_num, r_num.T, rtol=0, atol=1e-14):
        raise ValueError(f"R must be finite and symmetric, got {r_num.tolist()}")
    if not (r - r.T).is_zero_matrix:
        r = (r + r.T) / 2
    try:
        np.linalg.cholesky(r_num)
    except np.linalg.LinAlgError:
        raise ValueError(f"R must be positive definite, got {r_num.tolist()}") from None

    xs = tuple(sympy.Symbol(f"x{i}", real=True) for i in range(n))
    ls = tuple(sympy.Symbol(f"l{i}", real=True) for i in range(n))
    us = tuple(sympy.Symbol(f"u{i}", real=True) for i in range(m))
    ds = tuple(sympy.Symbol(f"d{i}", real=True) for i in range(n))
    w = sympy.Symbol("w", real=True)
    # simultaneous replacement of user symbols by internal ones
    rename = dict(zip(states, xs, strict=True)) | dict(zip(inputs, us, strict=True))
    a, b = a.xreplace(rename), b.xreplace(rename)

    low, high = input_bounds(m, input_low, input_high)
    return _pontryagin(xs, ls, us, ds, w, a, b, r, low, high)


def _pontryagin(xs: tuple, ls: tuple, us: tuple, ds: tuple, w: sympy.Symbol, a: sympy.Matrix,
                b: sympy.Matrix, r: sympy.Matrix, low: np.ndarray, high: np.ndarray
                ) -> Derivation:
    """H, u*, H* and the state+costate ODEs, without or with a box on the inputs.

    With finite limits (R diagonal), H is minimised over the box input by input, so
    u*_i = clip(-(R^{-1} B^T lambda)_i, low_i, high_i). The box does not depend on x, so by the
    envelope theorem the costate ODE is -dH/dx at that u*, and H* = 0 still holds for a free
    final time. Those ODEs are then written in the input symbols ``u``; the generated code
    assigns the clipped law to them first.
    """
    lam, uvec, dvec = sympy.Matrix(ls), sympy.Matrix(us), sympy.Matrix(ds)
    r_inv = r.inv()
    mm = b * r_inv * b.T
    flow = (lam.T * (a + b * uvec))[0]
    ham = w + (uvec.T * r * uvec)[0] / 2 + flow
    u_star = -r_inv * b.T * lam
    chol = r.cholesky(hermitian=False)
    g = chol.inv() * b.T * dvec
    common = dict(x=xs, lam=ls, u=us, d=ds, w=w, drift=a, input_matrix=b, input_weight=r,
                  hamiltonian=ham, optimal_control=u_star,
                  ray_slope=(dvec.T * a)[0], ray_factors=tuple(g),
                  input_low=tuple(low.tolist()), input_high=tuple(high.tolist()))
    if np.any(np.isfinite(low)) or np.any(np.isfinite(high)):
        if not r.is_diagonal():
            raise ValueError("input limits need a diagonal R (the box minimisation of H then "
                             "separates input by input); give a diagonal input_weight")
        return Derivation(**common, h_star=ham, state_ode=tuple(a + b * uvec),
                          costate_ode=tuple(-sympy.diff(flow, xi) for xi in xs),
                          running_cost=w + (uvec.T * r * uvec)[0] / 2)
    quad = (lam.T * mm * lam)[0]
    h_star = w + (lam.T * a)[0] - quad / 2
    return Derivation(**common, h_star=h_star,
                      state_ode=tuple(sympy.diff(h_star, li) for li in ls),
                      costate_ode=tuple(-sympy.diff(h_star, xi) for xi in xs),
                      running_cost=w + quad / 2)


def input_bounds(m: int, low: Sequence[float] | float | None,
                 high: Sequence[float] | float | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-input bounds (m,) from scalars, sequences or None (unbounded); ValueError if
    malformed (wrong length, NaN, low >= high)."""
    out = []
    for value, default, what in ((low, -np.inf, "input_low"), (high, np.inf, "input_high")):
        arr = np.full(m, default) if value is None else np.array(value, dtype=float, ndmin=1)
        if arr.shape == (1,) and m > 1:
            arr = np.full(m, arr[0])
        if arr.shape != (m,):
            raise ValueError(f"{what} needs 1 or {m} values (one per input), got {arr.size}")
        if np.any(np.isnan(arr)):
            raise ValueError(f"{what} must not be NaN")
        out.append(arr)
    if np.any(out[0] >= out[1]):
        raise ValueError(f"input limits need low < high for every input, got low "
                         f"{out[0].tolist()} and high {out[1].tolist()}")
    return out[0], out[1]


def limit_derivation(der: Derivation, input_low: Sequence[float] | float | None,
                     input_high: Sequence[float] | float | None) -> Derivation:
    """The derivation of the same system with the inputs confined to ``low <= u <= high``
    (None or +-inf: unbounded; see `_pontryagin`)."""
    low, high = input_bounds(der.m, input_low, input_high)
    return _pontryagin(der.x, der.lam, der.u, der.d, der.w, der.drift, der.input_matrix,
                       der.input_weight, low, high)
