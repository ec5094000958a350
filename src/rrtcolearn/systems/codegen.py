"""Code generation for a derived system: sympy's code printers (after ``sympy.cse``) write the
scalar numba kernels and the vectorised numpy functions of a `derivation.Derivation` into one
module text; `rrtcolearn.systems.generated` writes, caches and imports it. Only the printers
produce the generated text: no user string is ever evaluated or pasted into it.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np
import sympy
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.pycode import PythonCodePrinter

from rrtcolearn.integrate import KERNELS
from rrtcolearn.systems.derivation import Derivation


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
