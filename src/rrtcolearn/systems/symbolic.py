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
``$XDG_CACHE_HOME/rrtcolearn/systems`` or ``~/.cache/rrtcolearn/systems``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import sympy
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.pycode import PythonCodePrinter

from rrtcolearn.systems.base import System

__all__ = [
    "CostateParametrisation",
    "Derivation",
    "SymbolicSystem",
    "build_system",
    "derive",
    "generate_source",
    "generated_dir",
    "load_generated_module",
]

_MODULE_PREFIX = "rrtcolearn_sys_"


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
    optimal_control: sympy.Matrix  # u*(x, lambda), (m, 1)
    h_star: sympy.Expr  # H*(x, lambda)
    state_ode: tuple[sympy.Expr, ...]  # dH*/dlambda
    costate_ode: tuple[sympy.Expr, ...]  # -dH*/dx
    running_cost: sympy.Expr  # w + u*^T R u* / 2
    ray_slope: sympy.Expr  # p = d^T a(x)
    ray_factors: tuple[sympy.Expr, ...]  # g = L^{-1} B^T d with R = L L^T, so q = |g|^2

    @property
    def n(self) -> int:
        return len(self.x)

    @property
    def m(self) -> int:
        return len(self.u)


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
) -> Derivation:
    """Validate a definition and derive u*, H*, the state+costate ODEs and the ray terms.

    ``drift`` is a(x) (n entries), ``input_matrix`` B(x) (n x m), ``input_weight`` R (m x m,
    identity when None); ``parameters`` maps remaining symbols to numbers. ValueError explains
    a malformed definition (wrong shapes, unknown symbols, inputs inside a or B, R not constant
    symmetric positive definite).
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

    lam, uvec, dvec = sympy.Matrix(ls), sympy.Matrix(us), sympy.Matrix(ds)
    r_inv = r.inv()
    mm = b * r_inv * b.T
    ham = w + (uvec.T * r * uvec)[0] / 2 + (lam.T * (a + b * uvec))[0]
    u_star = -r_inv * b.T * lam
    quad = (lam.T * mm * lam)[0]
    h_star = w + (lam.T * a)[0] - quad / 2
    state_ode = tuple(sympy.diff(h_star, li) for li in ls)
    costate_ode = tuple(-sympy.diff(h_star, xi) for xi in xs)
    chol = r.cholesky(hermitian=False)
    g = chol.inv() * b.T * dvec
    return Derivation(
        x=xs, lam=ls, u=us, d=ds, w=w, drift=a, input_matrix=b, input_weight=r,
        hamiltonian=ham, optimal_control=u_star, h_star=h_star, state_ode=state_ode,
        costate_ode=costate_ode, running_cost=w + quad / 2,
        ray_slope=(dvec.T * a)[0], ray_factors=tuple(g),
    )


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


def generate_source(der: Derivation) -> str:
    """The generated module's text (deterministic: equal definitions give equal text)."""
    sp, vp = _ScalarPrinter({"strict": True}), _VectorPrinter({"strict": True})
    n, m = der.n, der.m
    xn = [str(s) for s in der.x]
    ln = [str(s) for s in der.lam]
    un = [str(s) for s in der.u]
    dn = [str(s) for s in der.d]
    u_star = list(der.optimal_control)
    f = list(der.drift + der.input_matrix * sympy.Matrix(der.u))
    ray = [der.ray_slope, *der.ray_factors]
    gn = [f"g{j}" for j in range(len(der.ray_factors))]
    q_scalar = " + ".join(f"{g} * {g}" for g in gn)
    L: list[str] = [
        '"""Generated by rrtcolearn.systems.symbolic from a sympy definition; do not edit.',
        "",
        "The file name is the SHA-256 of this text, so a changed definition gets a new file.",
        '"""',
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
        "",
        "",
        "@numba.njit(cache=True)",
        "def rhs(z, w, out):",
        "    # state+costate ODE under u*, running cost last",
        *_unpack(xn, "z"),
        *_unpack(ln, "z", n),
        *_assignments(sp, [*der.state_ode, *der.costate_ode, der.running_cost],
                      [f"out[{i}]" for i in range(2 * n + 1)]),
        "",
        "",
        "@numba.njit(cache=True)",
        "def input_max_abs(z):",
        *_unpack(xn, "z"),
        *_unpack(ln, "z", n),
        *_assignments(sp, u_star, [f"v{j}" for j in range(m)]),
        "    r = float(abs(v0))",
    ]
    for j in range(1, m):
        L += [f"    a{j} = float(abs(v{j}))", f"    if not (a{j} <= r):", f"        r = a{j}"]
    L += [
        "    return r",
        "",
        "",
        "@numba.njit(cache=True)",
        "def costate_from_params_jit(x, p, w, out):",
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
        "",
        "",
        "define_kernels(globals())  # rollout_jit, rollout_batch_jit",
        "",
        "",
        "def _f64(a):",
        "    return numpy.asarray(a, dtype=numpy.float64)",
        "",
        "",
        "def optimal_control(x, lam):",
        '    """u* = -R^{-1} B(x)^T lambda for (N, n) states and costates; (N, m)."""',
        "    x, lam = _f64(x), _f64(lam)",
        *_unpack(xn, "x", columns=True),
        *_unpack(ln, "lam", columns=True),
        f"    out = numpy.empty((x.shape[0], {m}))",
        *_assignments(vp, u_star, [f"out[:, {j}]" for j in range(m)]),
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
    return "\n".join(L)


# --------------------------------------------------------------------------- module cache


def generated_dir(cache_dir: str | os.PathLike | None = None) -> Path:
    """Directory of the generated system modules (see the module docstring)."""
    if cache_dir is not None:
        root = Path(cache_dir)
    elif os.environ.get("RRTCOLEARN_CACHE"):
        root = Path(os.environ["RRTCOLEARN_CACHE"])
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = (Path(xdg) if xdg else Path.home() / ".cache") / "rrtcolearn"
    return root / "systems"


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".py")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _ensure_file(directory: Path, name: str, source: str) -> Path:
    """The file ``directory/name`` holding ``source``; rewritten only when absent or different
    (rewriting would change its mtime and invalidate numba's cache)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    try:
        if path.read_text(encoding="utf-8") == source:
            return path
    except (OSError, UnicodeDecodeError):
        pass
    _write_atomic(path, source)
    return path


def load_generated_module(source: str, cache_dir: str | os.PathLike | None = None
                          ) -> ModuleType:
    """Import the generated ``source`` from the cache directory, writing it first if needed.

    A module already imported in this process from the same file is reused. When the cache
    directory is not writable a per-user directory under the system temp dir is used instead.
    """
    digest = hashlib.sha256(source.encode("utf-8")).hexdigest()
    modname = _MODULE_PREFIX + digest
    filename = modname + ".py"
    directory = generated_dir(cache_dir)
    try:
        path = _ensure_file(directory, filename, source)
    except OSError as exc:
        fallback = Path(tempfile.gettempdir()) / f"rrtcolearn-{os.getuid()}" / "systems"
        warnings.warn(f"cannot write generated system to {directory} ({exc}); using {fallback}",
                      RuntimeWarning, stacklevel=2)
        path = _ensure_file(fallback, filename, source)
    existing = sys.modules.get(modname)
    if existing is not None and getattr(existing, "__file__", None) == str(path):
        return existing
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:  # pragma: no cover - only for exotic filesystems
        raise ImportError(f"cannot import generated module {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(modname, None)
        raise
    return module


# --------------------------------------------------------------------------- System


# System field -> attribute of the generated module
_GENERATED = {
    "rhs": "rhs",
    "rollout_jit": "rollout_jit",
    "rollout_batch_jit": "rollout_batch_jit",
    "input_max_abs_jit": "input_max_abs",
    "costate_from_params": "costate_from_params",
    "costate_from_params_jit": "costate_from_params_jit",
    "optimal_control": "optimal_control",
    "hamiltonian": "hamiltonian",
    "dynamics": "dynamics",
}


@dataclass(frozen=True)
class CostateParametrisation:
    """A system author's costate parametrisation, used instead of the costate direction.

    names, low, high : the k steering parameters and their sampling box (low < high, finite).
    circular : which parameters live on a circle of period ``high - low``.
    from_params : ``(x (N,n), p (N,k), w) -> (lambda (N,n), valid (N,))``, vectorised numpy;
        valid costates must satisfy H* = 0.
    from_params_jit : ``(x (n,), p (k,), w, out (n,)) -> bool``, the scalar version, compiled
        with ``numba.njit(cache=True)``; writes the costate into ``out``.

    to_params : optional inverse ``(x (N,n), lambda (N,n)) -> p (N,k)`` (see
        `System.params_from_costate`).

    The functions should be module-level functions of an importable module, so that the
    system pickles (by reference) for spawned workers.
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    circular: tuple[bool, ...]
    from_params: Callable
    from_params_jit: Callable
    to_params: Callable | None = None

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
        if not (callable(self.from_params) and callable(self.from_params_jit)):
            raise ValueError("from_params and from_params_jit must be callable")
        for name, value in (("names", names), ("low", low), ("high", high),
                            ("circular", circular)):
            object.__setattr__(self, name, value)


def direction_from_costate(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The direction parameters (N, n) of costates on H* = 0: lambda / max_i |lambda_i|, in
    [-1, 1]^n (the positive scale on the ray is unique, so the direction determines it)."""
    lam = np.asarray(lam, dtype=np.float64)
    norm = np.abs(lam).max(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return lam / norm


@dataclass(frozen=True)
class _GeneratedRef:
    attr: str


def _is_generated(value: Any, modname: str, attr: str) -> bool:
    """Whether ``value`` is ``attr`` of the generated module ``modname`` (by name, not by
    identity: the module object in ``sys.modules`` may have been re-imported meanwhile)."""
    func = getattr(value, "py_func", value)  # numba dispatchers wrap the Python function
    return (getattr(func, "__module__", None) == modname
            and getattr(func, "__name__", None) == attr)


def _rebuild(cls: type, source: str, state: dict) -> SymbolicSystem:
    module = load_generated_module(source) if source else None
    kwargs = {k: getattr(module, v.attr) if isinstance(v, _GeneratedRef) else v
              for k, v in state.items()}
    return cls(**kwargs)


@dataclass(frozen=True)
class SymbolicSystem(System):
    """A `System` built by `build_system`, with its generated source and derivation.

    It pickles as the source plus its plain fields, so spawned or remote (Dask) workers
    rebuild the module from the source into their own cache; the generated module is not
    importable by name there.
    """

    source: str = field(default="", repr=False, compare=False)
    derivation: Derivation | None = field(default=None, repr=False, compare=False)

    def __reduce__(self):
        digest = hashlib.sha256(self.source.encode("utf-8")).hexdigest()
        modname = _MODULE_PREFIX + digest
        state = {}
        for f in fields(self):
            value = getattr(self, f.name)
            attr = _GENERATED.get(f.name)
            if self.source and attr is not None and _is_generated(value, modname, attr):
                value = _GeneratedRef(attr)
            state[f.name] = value
        return _rebuild, (type(self), self.source, state)


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
    state_names: Sequence[str] | None = None,
    input_names: Sequence[str] | None = None,
    description: str = "",
    defaults: dict | None = None,
    cache_dir: str | os.PathLike | None = None,
    costate_parametrisation: CostateParametrisation | None = None,
) -> SymbolicSystem:
    """Derive, generate, compile (lazily, cached) and wrap a system ``x' = a(x) + B(x) u``.

    ``drift`` = a(x) (n), ``input_matrix`` = B(x) (n x m), ``input_weight`` = R (m x m,
    identity by default); ``state_low``/``state_high`` is the start-state sampling box and
    ``angle_dims`` the coordinates with period 2*pi (the definition must be periodic in them).
    Names default to the symbols' names. The steering parameters are the costate direction's
    components ``d_<state>`` in [-1, 1] unless ``costate_parametrisation`` gives the author's
    own (module docstring).
    """
    der = derive(states, inputs, drift, input_matrix, input_weight, parameters)
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
    source = generate_source(der)
    module = load_generated_module(source, cache_dir)
    cp = costate_parametrisation
    if cp is None:
        params = dict(param_names=tuple(f"d_{s}" for s in s_names), param_low=-np.ones(n),
                      param_high=np.ones(n), param_circular=(False,) * n,
                      costate_from_params=module.costate_from_params,
                      costate_from_params_jit=module.costate_from_params_jit,
                      params_from_costate=direction_from_costate)
    else:
        params = dict(param_names=cp.names, param_low=np.array(cp.low),
                      param_high=np.array(cp.high), param_circular=cp.circular,
                      costate_from_params=cp.from_params,
                      costate_from_params_jit=cp.from_params_jit,
                      params_from_costate=cp.to_params)
    return SymbolicSystem(
        name=name,
        state_names=s_names,
        input_names=i_names,
        state_low=low,
        state_high=high,
        angle_dims=angles,
        **params,
        rhs=module.rhs,
        rollout_jit=module.rollout_jit,
        rollout_batch_jit=module.rollout_batch_jit,
        input_max_abs_jit=module.input_max_abs,
        optimal_control=module.optimal_control,
        hamiltonian=module.hamiltonian,
        dynamics=module.dynamics,
        description=description,
        defaults=dict(defaults or {}),
        source=source,
        derivation=der,
    )
