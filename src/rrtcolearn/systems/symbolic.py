"""Build a `System` from a sympy definition of an input-affine system.

The user gives ``x' = a(x) + B(x) u`` with running cost ``w + u^T R u / 2`` (``R`` constant,
symmetric positive definite) as sympy expressions in the state symbols, physical parameters
already numbers (or substituted through ``parameters``). Pontryagin's machinery is derived
symbolically:

    H   = w + u^T R u / 2 + lambda^T (a + B u),
    u*  = -R^{-1} B^T lambda,
    H*  = w + lambda^T a - lambda^T M lambda / 2,   M = B R^{-1} B^T,
    x'  = dH*/dlambda,   lambda' = -dH*/dx,   cost' = w + lambda^T M lambda / 2.

Code generation: sympy's code printers (after ``sympy.cse``) write the scalar kernels
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
import hashlib
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.pycode import PythonCodePrinter

from rrtcolearn.integrate import KERNELS
from rrtcolearn.systems.base import System
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
    "with_input_limits",
]

# --------------------------------------------------------------------------- derivation


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


# --------------------------------------------------------------------------- code generation


class _ScalarPrinter(PythonCodePrinter):
    """Plain Python with ``math`` functions; floats printed so that they round-trip."""

    def _print_Float(self, expr: sympy.Float) -> str:
        return repr(float(expr))


class _VectorPrinter(NumPyPrinter):
    """numpy code; floats printed so that they round-trip."""

    def _print_Float(self, expr: sympy.Float) -> str:
        return repr(float(expr))


def _assignments(printer, exprs: Sequence[sympy.Expr], targets: Sequence[str],
                 indent: str = "    ") -> list[str]:
    """``targets[i] = exprs[i]`` after common-subexpression elimination (temporaries c0, ...)."""
    exprs = [sympy.sympify(e) for e in exprs]
    temps, reduced = sympy.cse(exprs, symbols=sympy.numbered_symbols("c"))
    lines = [f"{indent}{sym} = {printer.doprint(e)}" for sym, e in temps]
    lines += [f"{indent}{t} = {printer.doprint(e)}" for t, e in zip(targets, reduced, strict=True)]
    return lines


def _unpack(names: Sequence[str], source: str, offset: int = 0, columns: bool = False,
            indent: str = "    ") -> list[str]:
    if columns:
        return [f"{indent}{v} = {source}[:, {i}]" for i, v in enumerate(names)]
    return [f"{indent}{v} = {source}[{offset + i}]" for i, v in enumerate(names)]


def _float_text(v: float) -> str:
    """A float literal that round-trips, infinities as ``math.inf``."""
    if np.isinf(v):
        return "math.inf" if v > 0 else "-math.inf"
    return repr(float(v))


_LINE_ROOT = '''

@numba.njit(cache=True)
def _line_root(alpha, beta, cz, cd, right):
    """Largest (right) or smallest root t of the concave piecewise-quadratic
    g(t) = alpha + beta t + sum_j min_{ULO_j <= u <= UHI_j} (RDIAG_j u^2 / 2 + (cz_j + t cd_j) u),
    H* along the costate line cz + t cd (in input coordinates B^T lambda); NaN if none."""
    m = cd.shape[0]
    bp = numpy.empty(2 * m)
    nb = 0
    for j in range(m):
        if cd[j] != 0.0:
            if math.isfinite(ULO[j]):
                bp[nb] = (-RDIAG[j] * ULO[j] - cz[j]) / cd[j]
                nb += 1
            if math.isfinite(UHI[j]):
                bp[nb] = (-RDIAG[j] * UHI[j] - cz[j]) / cd[j]
                nb += 1
    bps = numpy.sort(bp[:nb])
    for step in range(nb + 1):
        k = nb - step if right else step
        lo = -math.inf if k == 0 else bps[k - 1]
        hi = math.inf if k == nb else bps[k]
        if lo == -math.inf and hi == math.inf:
            tm = 0.0
        elif lo == -math.inf:
            tm = hi - 1.0
        elif hi == math.inf:
            tm = lo + 1.0
        else:
            tm = 0.5 * (lo + hi)
        qa = 0.0
        qb = beta
        qc = alpha
        for j in range(m):
            r = RDIAG[j]
            u = -(cz[j] + tm * cd[j]) / r
            if u < ULO[j] or u > UHI[j]:
                b = ULO[j] if u < ULO[j] else UHI[j]
                qc += 0.5 * r * b * b + cz[j] * b
                qb += cd[j] * b
            else:
                qa -= 0.5 * cd[j] * cd[j] / r
                qb -= cz[j] * cd[j] / r
                qc -= 0.5 * cz[j] * cz[j] / r
        slack = 1e-12 * (1.0 + abs(tm))
        if qa < 0.0:
            disc = qb * qb - 4.0 * qa * qc
            if disc < 0.0:
                continue
            sq = math.sqrt(disc)
            qq = -0.5 * (qb + (sq if qb >= 0.0 else -sq))
            t1 = qq / qa
            t2 = qc / qq if qq != 0.0 else t1
            first = max(t1, t2) if right else min(t1, t2)
            second = min(t1, t2) if right else max(t1, t2)
            if lo - slack <= first <= hi + slack:
                return first
            if lo - slack <= second <= hi + slack:
                return second
        elif qb != 0.0:
            t = -qc / qb
            if lo - slack <= t <= hi + slack:
                return t
    return math.nan
'''


def _clipped_control(printer, der: Derivation, indent: str = "    ") -> list[str]:
    """Scalar code assigning the clipped law u*_j = clip(free_j, ULO_j, UHI_j) to ``u<j>``."""
    un = [str(s) for s in der.u]
    lines = _assignments(printer, list(der.optimal_control), un, indent)
    for j, u in enumerate(un):
        if np.isfinite(der.input_low[j]):
            lines += [f"{indent}if {u} < ULO[{j}]:", f"{indent}    {u} = ULO[{j}]"]
        if np.isfinite(der.input_high[j]):
            lines += [f"{indent}if {u} > UHI[{j}]:", f"{indent}    {u} = UHI[{j}]"]
    return lines


def generate_source(der: Derivation, line: tuple | None = None) -> str:
    """The generated module's text (deterministic: equal definitions give equal text).

    ``line`` is a costate parametrisation's line, ``(p_symbols, lam0, direction, right,
    inverse)`` in the derivation's symbols (see `CostateParametrisation`); None for the
    default costate direction.
    """
    sp, vp = _ScalarPrinter({"strict": True}), _VectorPrinter({"strict": True})
    n, m = der.n, der.m
    sat = der.saturated
    xn = [str(s) for s in der.x]
    ln = [str(s) for s in der.lam]
    un = [str(s) for s in der.u]
    dn = [str(s) for s in der.d]
    u_star = list(der.optimal_control)
    f = list(der.drift + der.input_matrix * sympy.Matrix(der.u))
    ray = [der.ray_slope, *der.ray_factors]
    gn = [f"g{j}" for j in range(len(der.ray_factors))]
    q_scalar = " + ".join(f"{g} * {g}" for g in gn)
    # the control inside the kernels: the free law substituted (no limits), or clipped first
    u_lines = _clipped_control(sp, der) if sat else []
    L: list[str] = [
        '"""Generated by rrtcolearn.systems.symbolic from a sympy definition; do not edit.',
        "",
        "The file name is the SHA-256 of this text, so a changed definition gets a new file.",
        '"""',
        "",
        # the kernels compiled into this module (`define_kernels`) live in integrate.py; their
        # digest here makes a change to them a new file too, so numba's on-disk cache (keyed
        # by this file and each function's own bytecode, not its callees') is never stale
        f"# integrate kernels {hashlib.sha256(KERNELS.encode('utf-8')).hexdigest()[:16]}",
        "",
        "import math",
        "",
        "import numba",
        "import numpy",
        "",
        "from rrtcolearn.integrate import define_kernels",
        "",
        f"N_STATES = {n}",
        f"N_INPUTS = {m}",
    ]
    if sat or line is not None:
        rdiag = [float(der.input_weight[j, j]) for j in range(m)]
        L += [
            f"RDIAG = numpy.array([{', '.join(_float_text(v) for v in rdiag)}])",
            f"ULO = numpy.array([{', '.join(_float_text(v) for v in der.input_low)}])",
            f"UHI = numpy.array([{', '.join(_float_text(v) for v in der.input_high)}])",
        ]
    L += [
        "",
        "",
        "@numba.njit(cache=True)",
        "def rhs(z, w, out):",
        "    # state+costate ODE under u*, running cost last",
        *_unpack(xn, "z"),
        *_unpack(ln, "z", n),
        *u_lines,
        *_assignments(sp, [*der.state_ode, *der.costate_ode, der.running_cost],
                      [f"out[{i}]" for i in range(2 * n + 1)]),
        "",
        "",
        "@numba.njit(cache=True)",
        "def input_max_abs(z):",
        *_unpack(xn, "z"),
        *_unpack(ln, "z", n),
    ]
    if sat:
        L += [*u_lines, *[f"    v{j} = {u}" for j, u in enumerate(un)]]
    else:
        L += _assignments(sp, u_star, [f"v{j}" for j in range(m)])
    L += ["    r = float(abs(v0))"]
    for j in range(1, m):
        L += [f"    a{j} = float(abs(v{j}))", f"    if not (a{j} <= r):", f"        r = a{j}"]
    L += ["    return r", ""]
    if sat or line is not None:
        L += _LINE_ROOT.splitlines()
    L += ["", "", "@numba.njit(cache=True)", "def costate_from_params_jit(x, p, w, out):"]
    btd = list(der.input_matrix.T * sympy.Matrix(der.d))  # B^T d
    if line is None and not sat:
        L += [
            "    # lambda = s d on H* = 0 for the unit direction d = p / |p|",
            *_unpack(dn, "p"),
            f"    nrm = math.sqrt({' + '.join(f'{d} * {d}' for d in dn)})",
            "    if not (nrm > 0.0) or not math.isfinite(nrm):",
            "        return False",
            *[f"    {d} = {d} / nrm" for d in dn],
            *_unpack(xn, "x"),
            *_assignments(sp, ray, ["pp", *gn]),
            f"    q = {q_scalar}",
            "    r = math.sqrt(pp * pp + 2.0 * q * w)",
            "    if pp <= 0.0:",
            "        den = r - pp",
            "        s = 2.0 * w / den if den > 0.0 else -1.0",
            "    else:",
            "        s = (pp + r) / q if q > 0.0 else -1.0",
            "    if not (s > 0.0) or not math.isfinite(s):",
            "        return False",
            *[f"    out[{i}] = s * {d}" for i, d in enumerate(dn)],
            "    return True",
        ]
    elif line is None:
        L += [
            "    # lambda = s d on the saturated H* = 0: the positive root along the ray",
            *_unpack(dn, "p"),
            f"    nrm = math.sqrt({' + '.join(f'{d} * {d}' for d in dn)})",
            "    if not (nrm > 0.0) or not math.isfinite(nrm):",
            "        return False",
            *[f"    {d} = {d} / nrm" for d in dn],
            *_unpack(xn, "x"),
            f"    cz = numpy.zeros({m})",
            f"    cd = numpy.empty({m})",
            *_assignments(sp, [der.ray_slope, *btd], ["pp", *[f"cd[{j}]" for j in range(m)]]),
            "    s = _line_root(w, pp, cz, cd, True)",
            "    if not (s > 0.0) or not math.isfinite(s):",
            "        return False",
            *[f"    out[{i}] = s * {d}" for i, d in enumerate(dn)],
            "    return True",
        ]
    else:
        psyms, lam0, direction, right, _ = line
        lam0v, dirv = sympy.Matrix(lam0), sympy.Matrix(direction)
        a, b = der.drift, der.input_matrix
        exprs = [*lam0, *direction, right, (lam0v.T * a)[0], (dirv.T * a)[0],
                 *list(b.T * lam0v), *list(b.T * dirv)]
        targets = [*[f"e{i}" for i in range(n)], *[f"k{i}" for i in range(n)], "rt", "al",
                   "be", *[f"cz[{j}]" for j in range(m)], *[f"cd[{j}]" for j in range(m)]]
        L += [
            "    # lambda = lambda0(p) + t e(p) on H* = 0 (saturated when limited): the root on",
            "    # the side the parametrisation names",
            *_unpack([str(s) for s in psyms], "p"),
            *_unpack(xn, "x"),
            f"    cz = numpy.empty({m})",
            f"    cd = numpy.empty({m})",
            *_assignments(sp, exprs, targets),
            "    t = _line_root(w + al, be, cz, cd, rt >= 0.0)",
            "    if not math.isfinite(t):",
            "        return False",
            *[f"    out[{i}] = e{i} + t * k{i}" for i in range(n)],
            "    return True",
        ]
    L += [
        "",
        "",
        "@numba.njit(cache=True)",
        "def dynamics_jit(x, u, out):",
        "    # x' = a(x) + B(x) u for one state and a given input (planners that choose inputs)",
        *_unpack(xn, "x"),
        *_unpack(un, "u"),
        *_assignments(sp, f, [f"out[{i}]" for i in range(n)]),
        "",
        "",
        "define_kernels(globals())  # rollout_jit, rollout_batch_jit, propagate_jit, ...",
        "",
        "",
        "def _f64(a):",
        "    return numpy.asarray(a, dtype=numpy.float64)",
        "",
        "",
        "def optimal_control(x, lam):",
        '    """u* = argmin_u H over the input box, clip(-R^{-1} B(x)^T lambda), for (N, n)',
        '    states and costates; (N, m)."""',
        "    x, lam = _f64(x), _f64(lam)",
        *_unpack(xn, "x", columns=True),
        *_unpack(ln, "lam", columns=True),
        f"    out = numpy.empty((x.shape[0], {m}))",
        *_assignments(vp, u_star, [f"out[:, {j}]" for j in range(m)]),
    ]
    if sat:
        L += ["    numpy.clip(out, ULO, UHI, out=out)"]
    L += [
        "    return out",
        "",
        "",
        "def hamiltonian(x, lam, u, w):",
        '    """H = w + u^T R u / 2 + lambda^T (a(x) + B(x) u); (N,)."""',
        "    x, lam, u = _f64(x), _f64(lam), _f64(u)",
        *_unpack(xn, "x", columns=True),
        *_unpack(ln, "lam", columns=True),
        *_unpack(un, "u", columns=True),
        "    out = numpy.empty(x.shape[0])",
        *_assignments(vp, [der.hamiltonian], ["out[:]"]),
        "    return out",
        "",
        "",
        "def dynamics(x, u):",
        '    """x\' = a(x) + B(x) u; (N, n)."""',
        "    x, u = _f64(x), _f64(u)",
        *_unpack(xn, "x", columns=True),
        *_unpack(un, "u", columns=True),
        f"    out = numpy.empty((x.shape[0], {n}))",
        *_assignments(vp, f, [f"out[:, {i}]" for i in range(n)]),
        "    return out",
        "",
        "",
    ]
    if line is None and not sat:
        L += [
            "def costate_from_params(x, p, w):",
            '    """Costates (N, n) on H* = 0 along the directions p (N, n); also the valid mask.',
            "",
            "    Invalid rows (zero or non-finite direction, no positive root) are NaN.",
            '    """',
            "    x, p = _f64(x), _f64(p)",
            "    nrm = numpy.sqrt(numpy.sum(p * p, axis=1))",
            "    ok = numpy.isfinite(nrm) & (nrm > 0.0)",
            "    zero = numpy.zeros(x.shape[0])",
            "    with numpy.errstate(all='ignore'):",
            "        dir_ = p / numpy.where(ok, nrm, 1.0)[:, None]",
            *_unpack(dn, "dir_", columns=True, indent="        "),
            *_unpack(xn, "x", columns=True, indent="        "),
            *_assignments(vp, ray, ["pp", *gn], indent="        "),
            "        pp = pp + zero",
            f"        q = numpy.maximum({' + '.join(f'{g} * {g}' for g in gn)} + zero, 0.0)",
            "        r = numpy.sqrt(pp * pp + 2.0 * q * w)",
            "        s = numpy.where(pp <= 0.0, 2.0 * w / (r - pp), (pp + r) / q)",
            "    valid = ok & numpy.isfinite(s) & (s > 0.0)",
            "    lam = numpy.where(valid[:, None], s[:, None] * dir_, numpy.nan)",
            "    return lam, valid",
            "",
        ]
    else:
        L += [
            "@numba.njit(cache=True)",
            "def _costate_batch(x, p, w, lam, valid):",
            "    for i in range(x.shape[0]):",
            "        valid[i] = costate_from_params_jit(x[i], p[i], w, lam[i])",
            "",
            "",
            "def costate_from_params(x, p, w):",
            '    """Costates (N, n) on H* = 0 for the parameters p (N, k); also the valid mask.',
            "",
            "    Invalid rows (no root on the parametrised line or ray) are NaN.",
            '    """',
            "    x = numpy.ascontiguousarray(x, dtype=numpy.float64)",
            "    p = numpy.ascontiguousarray(p, dtype=numpy.float64)",
            f"    lam = numpy.empty((x.shape[0], {n}))",
            "    valid = numpy.zeros(x.shape[0], dtype=numpy.bool_)",
            "    _costate_batch(x, p, float(w), lam, valid)",
            "    lam[~valid] = numpy.nan",
            "    return lam, valid",
            "",
        ]
    if line is not None and line[4] is not None:
        psyms, inverse = line[0], line[4]
        vn = [f"v{i}" for i in range(n)]
        L += [
            "",
            "def params_from_costate(x, lam):",
            '    """The parameters (N, k) of costates (N, n) on H* = 0 (inverse of',
            '    costate_from_params), given the state derivative v = x\' under u*."""',
            "    x, lam = _f64(x), _f64(lam)",
            "    v = dynamics(x, optimal_control(x, lam))",
            *_unpack(xn, "x", columns=True),
            *_unpack(ln, "lam", columns=True),
            *_unpack(vn, "v", columns=True),
            f"    out = numpy.empty((x.shape[0], {len(psyms)}))",
            *_assignments(vp, list(inverse),
                          [f"out[:, {i}]" for i in range(len(psyms))]),
            "    return out",
            "",
        ]
    return "\n".join(L)


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


def _generated_fields(der: Derivation, cp: CostateParametrisation | None,
                      cache_dir: str | os.PathLike | None) -> dict:
    """The `System` fields that come from the generated module of ``der`` (and ``cp``)."""
    n = der.n
    line = None if cp is None else cp.expressions(der)
    source = generate_source(der, line)
    module = load_generated_module(source, cache_dir)
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
        invariant_coordinates=invariant_coordinates(der, line),
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
