"""Reference optimum of any `SymbolicSystem` query by direct collocation (CasADi + IPOPT).

The optimal control problem, for the system's own dynamics x' = a(x) + B(x) u and input
weight R (its sympy `Derivation`, converted to CasADi expressions by `sympy_to_casadi`):

    minimise  w T + integral_0^T u^T R u / 2 dt     over the free final time T,
    x(0) = start,  x(T) in the goal region,
    input box (the system's limits, tightened by ``u_max``), state box (non-angle
    coordinates; by default the system's box, the planner's default state constraints).

The goal region is a point (``tolerance = 0``), the ball ``|W (x - goal)| <= tolerance``
(weights W = ``goal_weights``, 0 = free coordinate) or ``goal_distance(x) <= tolerance`` for
a user-supplied CasADi-compatible distance (e.g. a task-space goal). With ``wrap_goal``
angle coordinates are compared modulo a turn, exactly as `PlanningProblem.goal_offset`
does: a wrapped offset d_j in [-pi, pi] is a variable, tied to the end state by
sin(x_j(T) - g_j - d_j) = 0 and cos(x_j(T) - g_j - d_j) >= 0 (so x_j(T) = g_j + d_j + 2 pi k
for some integer k, which the solver chooses; both constraints are smooth with non-zero
gradients, unlike 1 - cos(...) = 0).

Transcription: compressed Hermite-Simpson on N equal intervals (as `baselines.direct`):
states at the N + 1 nodes, controls at the nodes and the N midpoints (u(t) the quadratic
through them on each interval), Simpson's rule for the running cost; state bounds at the
nodes. IPOPT with exact Hessians. Several initial guesses are solved (straight lines in the
state space to the goal at several durations, optionally a given path resampled onto the
grid) and the cheapest converged solution is kept.

Independent check: the winning controls are re-simulated with RK4 on the system's generated
numpy dynamics (not the CasADi expressions), once with the continuous control u(t) (small
steps: the transcription error) and once held piecewise constant for 0.01 s steps as a
planner would execute them (`rrtcolearn.integrate.propagate_controls`).

``import casadi`` happens inside functions only: the package is the optional extra ``direct``.
See docs/collocation.md for the measured optima and the choices.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rrtcolearn.integrate import propagate_controls

N_INTERVALS = 100
DURATIONS = (1.0, 2.0, 4.0, 8.0)
T_MIN = 0.01
HELD_DT = 0.01
_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")

__all__ = ["CollocationResult", "optimal_cost", "problem_optimum", "sympy_to_casadi"]


# ----------------------------------------------------------------------------------------------
# sympy -> casadi


def _casadi_functions() -> dict[str, Callable]:
    import casadi as ca

    def fold(op):
        return lambda *args: _fold(op, args)

    return {
        "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "asin": ca.asin, "acos": ca.acos,
        "atan": ca.atan, "atan2": ca.atan2, "sinh": ca.sinh, "cosh": ca.cosh,
        "tanh": ca.tanh, "asinh": ca.asinh, "acosh": ca.acosh, "atanh": ca.atanh,
        "exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt, "Abs": ca.fabs, "sign": ca.sign,
        "floor": ca.floor, "ceiling": ca.ceil, "erf": ca.erf,
        "sec": lambda x: 1 / ca.cos(x), "csc": lambda x: 1 / ca.sin(x),
        "cot": lambda x: 1 / ca.tan(x), "Min": fold(ca.fmin), "Max": fold(ca.fmax),
        "Heaviside": lambda x, *h: ca.if_else(x > 0, 1.0, ca.if_else(x < 0, 0.0,
                                                                     float(h[0]) if h else 0.5)),
    }


def _fold(op, args):
    out = args[0]
    for a in args[1:]:
        out = op(out, a)
    return out


def sympy_to_casadi(expr: Any, symbols: dict) -> Any:
    """The CasADi expression of the sympy expression ``expr``, with ``symbols`` mapping sympy
    symbols to CasADi ones (SX or MX). Handles numbers, pi, E, +, *, powers (square roots as
    ``sqrt``), the elementary functions, Abs, sign, Min, Max, floor, ceiling, Heaviside and
    Piecewise with relational conditions; ValueError names anything else. Shared
    subexpressions are converted once."""
    import casadi as ca
    import sympy

    funcs = _casadi_functions()
    memo: dict = dict(symbols)

    def cond(c):
        if c is sympy.true:
            return 1.0
        if c is sympy.false:
            return 0.0
        if isinstance(c, sympy.And):
            return _fold(ca.logic_and, [cond(a) for a in c.args])
        if isinstance(c, sympy.Or):
            return _fold(ca.logic_or, [cond(a) for a in c.args])
        if isinstance(c, sympy.Not):
            return ca.logic_not(cond(c.args[0]))
        ops = {sympy.StrictLessThan: ca.lt, sympy.LessThan: ca.le,
               sympy.StrictGreaterThan: ca.gt, sympy.GreaterThan: ca.ge,
               sympy.Equality: ca.eq, sympy.Unequality: ca.ne}
        for cls, op in ops.items():
            if isinstance(c, cls):
                return op(conv(c.lhs), conv(c.rhs))
        raise ValueError(f"cannot convert the condition {c} to CasADi")

    def conv(e):
        if e in memo:
            return memo[e]
        if e.is_Symbol:
            raise ValueError(f"the symbol {e} has no CasADi counterpart (not a state or input)")
        if e.is_Number or isinstance(e, sympy.NumberSymbol):
            value = float(e)
            if not math.isfinite(value):
                raise ValueError(f"cannot convert the non-finite number {e} to CasADi")
            out = value
        elif e.is_Add:
            out = _fold(lambda a, b: a + b, [conv(a) for a in e.args])
        elif e.is_Mul:
            out = _fold(lambda a, b: a * b, [conv(a) for a in e.args])
        elif e.is_Pow:
            base, exponent = e.args
            if exponent == sympy.Rational(1, 2):
                out = ca.sqrt(conv(base))
            elif exponent == sympy.Rational(-1, 2):
                out = 1 / ca.sqrt(conv(base))
            elif exponent == -1:
                out = 1 / conv(base)
            else:
                out = conv(base) ** conv(exponent)
        elif isinstance(e, sympy.Piecewise):
            out = None
            for piece, c in reversed(e.args):
                value = conv(piece)
                out = value if out is None and c is sympy.true else ca.if_else(
                    cond(c), value, math.nan if out is None else out)
        elif type(e).__name__ in funcs:
            out = funcs[type(e).__name__](*[conv(a) for a in e.args])
        else:
            raise ValueError(f"cannot convert {type(e).__name__} ({e}) to CasADi; supported: "
                             "numbers, +, *, powers, Piecewise, " + ", ".join(sorted(funcs)))
        memo[e] = out
        return out

    return conv(sympy.sympify(expr))


def casadi_dynamics(system) -> tuple[Any, np.ndarray]:
    """(f, R): the CasADi Function f(x, u) = a(x) + B(x) u of a `SymbolicSystem` (from its
    sympy derivation) and its input weight R (m, m); checked against ``system.dynamics`` at
    random states and inputs."""
    import casadi as ca

    symbolic = getattr(system, "symbolic", None)
    der = symbolic()[0] if symbolic is not None else None
    if der is None:
        raise ValueError(f"system {system.name!r} has no sympy derivation: the collocation "
                         "needs a SymbolicSystem (built by rrtcolearn.systems.symbolic."
                         "build_system)")
    n, m = der.n, der.m
    x = ca.SX.sym("x", n)
    u = ca.SX.sym("u", m)
    table = {s: x[i] for i, s in enumerate(der.x)}
    a = [sympy_to_casadi(der.drift[i, 0], table) for i in range(n)]
    b = [[sympy_to_casadi(der.input_matrix[i, j], table) for j in range(m)] for i in range(n)]
    rhs = ca.vertcat(*[a[i] + sum(b[i][j] * u[j] for j in range(m)) for i in range(n)])
    f = ca.Function("f", [x, u], [rhs])
    r = np.array(der.input_weight.evalf(), dtype=np.float64)
    # the conversion against the system's generated numpy dynamics
    rng = np.random.default_rng(0)
    xs = rng.uniform(system.state_low, system.state_high, (8, n))
    us = rng.normal(size=(8, m))
    want = np.asarray(system.dynamics(xs, us), dtype=np.float64)
    got = np.asarray(f.map(8)(xs.T, us.T), dtype=np.float64).T
    if not np.allclose(got, want, rtol=1e-9, atol=1e-9 * (1 + np.abs(want).max())):
        raise ValueError(f"the CasADi dynamics of {system.name!r} differ from its generated "
                         f"ones (max difference {np.abs(got - want).max():g})")
    return f, r


# ----------------------------------------------------------------------------------------------
# result


@dataclass
class CollocationResult:
    """The cheapest converged solution over all initial guesses (``success`` False, and the
    cheapest attempt's values, when none converged).

    ``states`` (N+1, n) and ``controls`` (N+1, m) are at the nodes ``times``,
    ``mid_controls`` (N, m) at the interval midpoints; ``guess`` names the winning initial
    guess; ``attempts`` holds one dict per guess (guess, status, cost, duration, iterations,
    cpu_s). ``cpu_s`` is the process CPU of the whole call (building the NLP included).
    Independent checks, on the system's numpy dynamics: ``resim_error`` the largest
    difference between the collocation's end state and RK4 under the continuous control
    (steps of at most 2 ms; it grows with an unstable system's horizon), ``interval_error``
    the largest such difference over single intervals, each re-simulated from its node (the
    transcription's local error), ``resim_goal_distance`` that end state's distance to the goal
    region, ``resim_cost`` the cost of the continuous control integrated exactly (3-point
    Gauss-Legendre per interval); ``held_error`` the end-state difference when the control is
    held constant for steps of about 0.01 s (the planners' execution).
    """

    success: bool
    status: str
    cost: float
    duration: float
    times: np.ndarray
    states: np.ndarray
    controls: np.ndarray
    mid_controls: np.ndarray
    guess: str
    n_intervals: int
    cpu_s: float
    attempts: list[dict] = field(default_factory=list, repr=False)
    resim_error: float = math.nan
    interval_error: float = math.nan
    resim_goal_distance: float = math.nan
    resim_cost: float = math.nan
    held_error: float = math.nan
    goal_distance: float = math.nan

    def control_at(self, t: np.ndarray) -> np.ndarray:
        """u(t) (K, m) at times t (K,): the quadratic through (u_k, u_k+1/2, u_k+1) on each
        interval, t clipped to [0, T]."""
        n = self.n_intervals
        s = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration) * (n / self.duration)
        k = np.minimum(np.floor(s).astype(np.int64), n - 1)
        tau = (s - k)[:, None]
        u0, um, u1 = self.controls[k], self.mid_controls[k], self.controls[k + 1]
        return (u0 * (2 * tau - 1) * (tau - 1) + um * 4 * tau * (1 - tau)
                + u1 * tau * (2 * tau - 1))

    def summary(self) -> dict:
        """The scalar figures as a JSON-friendly dict."""
        keys = ("success", "status", "cost", "duration", "guess", "n_intervals", "cpu_s",
                "resim_error", "interval_error", "resim_goal_distance", "resim_cost", "held_error",
                "goal_distance")
        return {k: getattr(self, k) for k in keys} | {"guesses": len(self.attempts)}


# ----------------------------------------------------------------------------------------------
# the NLP


class _Transcription:
    """The NLP of one problem structure, built once and solved from every guess.

    z = (T, vec(X) (n, N+1), vec(U) (m, N+1), vec(Um) (m, N), D (wrapped goal offsets));
    the start, goal, time weight and tolerance are NLP parameters.
    """

    def __init__(self, f, r: np.ndarray, n: int, m: int, n_intervals: int,
                 wrap: Sequence[int], weights: np.ndarray, mode: str,
                 goal_distance: Callable | None, max_iter: int, ipopt: dict | None):
        import casadi as ca

        self.n, self.m, self.N = n, m, int(n_intervals)
        N = self.N
        self.wrap = tuple(wrap)
        nw = len(self.wrap)
        T = ca.SX.sym("T")
        X = ca.SX.sym("X", n, N + 1)
        U = ca.SX.sym("U", m, N + 1)
        Um = ca.SX.sym("Um", m, N)
        D = ca.SX.sym("D", nw)
        x0 = ca.SX.sym("x0", n)
        goal = ca.SX.sym("goal", n)
        w = ca.SX.sym("w")
        tol = ca.SX.sym("tol")
        h = T / N
        fm = f.map(N + 1)
        F = fm(X, U)
        Xm = 0.5 * (X[:, :-1] + X[:, 1:]) + h / 8.0 * (F[:, :-1] - F[:, 1:])
        Fm = f.map(N)(Xm, Um)
        defects = X[:, 1:] - X[:, :-1] - h / 6.0 * (F[:, :-1] + 4.0 * Fm + F[:, 1:])
        rs = ca.DM(r)

        def quad(V):
            return 0.5 * ca.sum1(V * ca.mtimes(rs, V))

        J = w * T + h / 6.0 * ca.sum2(quad(U[:, :-1]) + 4.0 * quad(Um) + quad(U[:, 1:]))
        g = [ca.vec(defects), X[:, 0] - x0]
        lbg = [np.zeros(n * N), np.zeros(n)]
        ubg = [np.zeros(n * N), np.zeros(n)]
        xT = X[:, -1]
        offset = [xT[i] - goal[i] for i in range(n)]
        for k, j in enumerate(self.wrap):  # x_j(T) = goal_j + D_k + 2 pi (integer)
            phase = xT[j] - goal[j] - D[k]
            g += [ca.sin(phase), ca.cos(phase)]
            lbg += [[0.0], [0.0]]
            ubg += [[0.0], [np.inf]]
            offset[j] = D[k]
        if mode == "task":
            g.append(goal_distance(xT) - tol)
            lbg.append([-np.inf])
            ubg.append([0.0])
        elif mode == "point":
            rows = [i for i in range(n) if weights[i] > 0 and i not in self.wrap]
            if rows:
                g.append(ca.vertcat(*[offset[i] for i in rows]))
                lbg.append(np.zeros(len(rows)))
                ubg.append(np.zeros(len(rows)))
        else:  # ball
            g.append(sum((weights[i] * offset[i]) ** 2 for i in range(n)) - tol**2)
            lbg.append([-np.inf])
            ubg.append([0.0])
        z = ca.vertcat(T, ca.vec(X), ca.vec(U), ca.vec(Um), D)
        opts = {"print_time": 0, "ipopt.print_level": 0, "ipopt.sb": "yes",
                "ipopt.max_iter": int(max_iter)}
        opts.update({f"ipopt.{k}": v for k, v in (ipopt or {}).items()})
        self.solver = ca.nlpsol("collocation", "ipopt",
                                {"x": z, "p": ca.vertcat(x0, goal, w, tol), "f": J,
                                 "g": ca.vertcat(*g)}, opts)
        self.lbg = np.concatenate([np.ravel(v) for v in lbg])
        self.ubg = np.concatenate([np.ravel(v) for v in ubg])
        self.n_vars = int(z.numel())
        self.ix = 1
        self.iu = self.ix + n * (N + 1)
        self.ium = self.iu + m * (N + 1)
        self.id = self.ium + m * N

    def pack(self, T: float, X: np.ndarray, U: np.ndarray, Um: np.ndarray,
             D: np.ndarray) -> np.ndarray:
        return np.concatenate([[T], X.ravel(), U.ravel(), Um.ravel(), D])

    def unpack(self, z: np.ndarray):
        n, m, N = self.n, self.m, self.N
        return (float(z[0]), z[self.ix:self.iu].reshape(N + 1, n),
                z[self.iu:self.ium].reshape(N + 1, m), z[self.ium:self.id].reshape(N, m),
                z[self.id:])


# ----------------------------------------------------------------------------------------------
# guesses and checks


def _unpacked_result(nlp: _Transcription, z: np.ndarray) -> CollocationResult:
    T, X, U, Um, _ = nlp.unpack(z)
    return CollocationResult(success=False, status="", cost=math.nan, duration=T,
                             times=np.linspace(0.0, T, nlp.N + 1), states=X, controls=U,
                             mid_controls=Um, guess="", n_intervals=nlp.N, cpu_s=0.0)


def _line_guess(start, target, duration, N, m):
    s = np.linspace(0.0, 1.0, N + 1)[:, None]
    return duration, start + (target - start) * s, np.zeros((N + 1, m)), np.zeros((N, m))


def _path_guess(path, N, m, angles):
    if isinstance(path, CollocationResult):  # its own interpolants: states linear, u(t)
        nodes = np.linspace(0.0, path.duration, N + 1)
        mids = 0.5 * (nodes[:-1] + nodes[1:])
        X = np.stack([np.interp(nodes, path.times, path.states[:, i])
                      for i in range(path.states.shape[1])], axis=1)
        return path.duration, X, path.control_at(nodes), path.control_at(mids)
    try:
        times, states, controls = (np.asarray(a, dtype=np.float64) for a in path)
    except (TypeError, ValueError):
        raise ValueError("path must be (times (K,), states (K, n), controls (K-1 or K, m))"
                         ) from None
    if times.ndim != 1 or len(times) < 2 or not np.all(np.diff(times) >= 0) \
            or not np.all(np.isfinite(times)) or not times[-1] > times[0]:
        raise ValueError("path times must be at least 2 finite increasing numbers")
    if len(states) == len(times) and len(controls) in (len(times) - 1, len(times)):
        # a re-simulated path (`evaluate.sample_path`) repeats the node where two edges
        # join, at one time: the later copy kept, whose input is the next edge's
        keep = np.r_[np.diff(times) > 0, True]
        times, states = times[keep], states[keep]
        controls = controls[keep[: len(controls)]]
    if states.ndim != 2 or len(states) != len(times) or not np.all(np.isfinite(states)):
        raise ValueError(f"path states must be ({len(times)}, n) finite numbers, got shape "
                         f"{states.shape}")
    controls = controls.reshape(len(controls), -1) if controls.ndim else controls
    if controls.ndim != 2 or controls.shape[1] != m or \
            len(controls) not in (len(times) - 1, len(times)) or \
            not np.all(np.isfinite(controls)):
        raise ValueError(f"path controls must be ({len(times) - 1} or {len(times)}, {m}) "
                         f"finite numbers, got shape {controls.shape}")
    states = states.copy()
    for j in angles:
        states[:, j] = np.unwrap(states[:, j])
    t = times - times[0]
    duration = float(t[-1])
    nodes = np.linspace(0.0, duration, N + 1)
    mids = 0.5 * (nodes[:-1] + nodes[1:])
    X = np.stack([np.interp(nodes, t, states[:, i]) for i in range(states.shape[1])], axis=1)

    def held(tq):  # control held over [t_k, t_k+1)
        k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(controls) - 1)
        return controls[k]

    return duration, X, held(nodes), held(mids)


def _rk4_resim(system, x0, result, max_step=0.002):
    """End state of RK4 on ``system.dynamics`` under the continuous control u(t)."""
    k = max(1, math.ceil(result.duration / max_step))
    dt = result.duration / k
    x = np.array(x0, dtype=np.float64)[None]
    t = 0.0

    def f(xx, tt):
        return np.asarray(system.dynamics(xx, result.control_at(np.array([tt]))))

    for _ in range(k):
        k1 = f(x, t)
        k2 = f(x + 0.5 * dt * k1, t + 0.5 * dt)
        k3 = f(x + 0.5 * dt * k2, t + 0.5 * dt)
        k4 = f(x + dt * k3, t + dt)
        x = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
    return x[0]


def _interval_error(system, result, max_step=0.002):
    """Largest difference (over the intervals and coordinates) between each node state and
    RK4 from the previous node under the continuous control: the local transcription error,
    free of the growth an unstable system gives the open-loop re-simulation."""
    N = result.n_intervals
    h = result.duration / N
    k = max(1, math.ceil(h / max_step))
    dt = h / k
    x = np.array(result.states[:-1], dtype=np.float64)
    t0 = result.times[:-1]

    def f(xx, tt):
        return np.asarray(system.dynamics(xx, result.control_at(tt)))

    for i in range(k):
        t = t0 + i * dt
        k1 = f(x, t)
        k2 = f(x + 0.5 * dt * k1, t + 0.5 * dt)
        k3 = f(x + 0.5 * dt * k2, t + 0.5 * dt)
        k4 = f(x + dt * k3, t + dt)
        x = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return float(np.abs(x - result.states[1:]).max())


def _exact_cost(result, r, w):
    """w T + the integral of u^T R u / 2 for the piecewise-quadratic control (exact:
    3-point Gauss-Legendre is exact for the quartic integrand)."""
    nodes, weights = np.polynomial.legendre.leggauss(3)
    h = result.duration / result.n_intervals
    left = np.arange(result.n_intervals) * h
    tq = (left[:, None] + 0.5 * h * (nodes[None] + 1.0)).ravel()
    u = result.control_at(tq)
    running = 0.5 * np.einsum("ki,ij,kj->k", u, r, u).reshape(-1, 3)
    return float(w * result.duration + 0.5 * h * (running * weights).sum())


# ----------------------------------------------------------------------------------------------
# public entry points


def _as_vector(value, n, what):
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} numbers, got {value!r}") from None
    if v.shape != (n,):
        raise ValueError(f"{what} must have {n} coordinates, got shape {v.shape}")
    return v


def _bounds_vector(value, default, n, what):
    if value is None:
        return np.array(default, dtype=np.float64)
    if len(value) != n:
        raise ValueError(f"{what} needs {n} values (None entries: the default), got "
                         f"{len(value)}")
    return np.array([d if v is None else float(v) for v, d in zip(value, default,
                                                                   strict=True)])


def optimal_cost(system, start, goal, *, tolerance: float = 0.0, time_weight: float = 1.0,
                 u_max: float | Sequence[float] | None = None,
                 state_low: Sequence[float | None] | None = None,
                 state_high: Sequence[float | None] | None = None,
                 wrap_goal: bool = True, goal_weights: Sequence[float] | None = None,
                 goal_distance: Callable[[Any], Any] | None = None,
                 n_intervals: int = N_INTERVALS, durations: Sequence[float] = DURATIONS,
                 turns: Sequence[int] = (0,), path: tuple | None = None,
                 t_min: float = T_MIN, t_max: float | None = None,
                 fixed_first: bool = True, search_intervals: int | None = None,
                 refine_best: int = 2, max_iter: int = 1000,
                 ipopt: dict | None = None) -> CollocationResult:
    """The minimum of ``time_weight * T + integral u^T R u / 2`` from ``start`` to the goal
    region, by Hermite-Simpson collocation on ``n_intervals`` intervals and IPOPT.

    Goal region: the point ``goal`` (``tolerance`` 0), the ball ``|W (x(T) - goal)| <=
    tolerance`` (W = ``goal_weights``, default all 1, 0 for a free coordinate) or, with
    ``goal_distance``, ``goal_distance(x(T)) <= tolerance``, where ``goal_distance`` maps a
    CasADi column vector (n,) to a CasADi scalar (numpy-only functions such as a planner's
    ``goal_fn`` cannot be used; write it with ``casadi`` functions). With ``wrap_goal`` angle
    coordinates (``system.angle_dims``) count modulo a turn.

    Inputs: the system's limits, tightened to ``|u_i| <= u_max`` (a number or one per
    input). States: ``state_low``/``state_high`` (n values, None entries keep the default)
    bound the non-angle coordinates at every node; default the system's box there, as
    `PlanningProblem` constrains a planner's states (pass +-inf to lift a bound).

    Guesses: a straight line in the state space from ``start`` to the goal (its angle
    coordinates the representative nearest the start, moved by each of ``turns`` whole
    turns), zero control, at each duration of ``durations``; and ``path`` = (times (K,),
    states (K, n), controls (K-1 or K, m), controls held over each step) resampled onto the
    grid (or a `CollocationResult`, e.g. of a coarser solve). T is free in [``t_min``,
    ``t_max``] (default 2 x the longest guess duration).
    With ``fixed_first`` each guess is first solved with T fixed to its duration, and the
    free-time problem starts from that solution (from a poor guess IPOPT otherwise tends to
    shrink T towards ``t_min`` and stop at a local infeasibility).
    With ``search_intervals`` (< ``n_intervals``) every guess is solved on that coarser grid
    first and only the ``refine_best`` cheapest distinct converged solutions are solved again
    on ``n_intervals`` (from their own interpolants), beside ``path`` solved on
    ``n_intervals`` directly: a wide search at a fraction of the CPU.
    ``max_iter`` bounds IPOPT's iterations per solve, ``ipopt`` adds IPOPT options.
    Returns the cheapest converged solution (`CollocationResult`), checked by
    re-simulation.
    """
    cpu0 = time.process_time()
    f, r = casadi_dynamics(system)
    n, m = system.n_states, system.n_inputs
    start = _as_vector(start, n, "start")
    goal = _as_vector(goal, n, "goal")
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))):
        raise ValueError("start and goal must be finite")
    tolerance = float(tolerance)
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be a non-negative number, got {tolerance!r}")
    time_weight = float(time_weight)
    if not (math.isfinite(time_weight) and time_weight > 0):
        raise ValueError(f"time_weight must be positive (a free final time needs it), got "
                         f"{time_weight!r}")
    if goal_distance is not None and tolerance <= 0:
        raise ValueError("a goal_distance needs a positive tolerance (the region is "
                         "goal_distance(x) <= tolerance)")
    if goal_distance is not None and not callable(goal_distance):
        raise ValueError("goal_distance must be a callable of a CasADi vector")
    weights = np.ones(n) if goal_weights is None else _as_vector(goal_weights, n,
                                                                  "goal_weights")
    if not (np.all(np.isfinite(weights)) and np.all(weights >= 0) and np.any(weights > 0)):
        raise ValueError("goal_weights must be finite, non-negative and not all zero")
    n_intervals = int(n_intervals)
    if n_intervals < 2 or (search_intervals is not None and int(search_intervals) < 2):
        raise ValueError(f"n_intervals and search_intervals must be at least 2, got "
                         f"{n_intervals} and {search_intervals}")
    if int(refine_best) < 1:
        raise ValueError(f"refine_best must be at least 1, got {refine_best}")
    durations = [float(d) for d in durations]
    if any(not (math.isfinite(d) and d > 0) for d in durations):
        raise ValueError(f"durations must be positive numbers, got {durations}")
    if not durations and path is None:
        raise ValueError("give at least one duration or a path to start from")
    turns = [int(k) for k in turns] or [0]

    # input and state bounds
    u_low, u_high = system.input_limits()
    if u_max is not None:
        cap = np.broadcast_to(np.asarray(u_max, dtype=np.float64), (m,)) \
            if np.ndim(u_max) == 0 or len(u_max) == m else None
        if cap is None or not np.all(cap > 0):
            raise ValueError(f"u_max must be a positive number or {m} of them, got {u_max!r}")
        u_low, u_high = np.maximum(u_low, -cap), np.minimum(u_high, cap)
    angles = tuple(int(j) for j in system.angle_dims)
    box_low = np.where(np.isin(np.arange(n), angles), -np.inf, system.state_low)
    box_high = np.where(np.isin(np.arange(n), angles), np.inf, system.state_high)
    x_low = _bounds_vector(state_low, box_low, n, "state_low")
    x_high = _bounds_vector(state_high, box_high, n, "state_high")
    x_low[list(angles)], x_high[list(angles)] = -np.inf, np.inf
    if np.any(x_low >= x_high):
        raise ValueError(f"state bounds need low < high, got {x_low} and {x_high}")
    if np.any(start < x_low) or np.any(start > x_high):
        raise ValueError(f"start {start.tolist()} is outside the state bounds")

    wrap = angles if (wrap_goal and goal_distance is None) else ()
    mode = "task" if goal_distance is not None else ("point" if tolerance == 0 else "ball")
    if mode == "point":
        free = [i for i in range(n) if weights[i] == 0 or i in wrap]
        fixed = np.setdiff1d(np.arange(n), free)
        if np.any(goal[fixed] < x_low[fixed]) or np.any(goal[fixed] > x_high[fixed]):
            raise ValueError(f"the goal {goal.tolist()} is outside the state bounds")
    if path is not None and not isinstance(path, CollocationResult):
        _path_guess(path, 2, m, angles)  # validated before any NLP is built
    path_duration = [] if path is None else [
        path.duration if isinstance(path, CollocationResult)
        else float(np.ptp(np.asarray(path[0], dtype=float)))]
    longest = max(durations + path_duration)
    t_max = 2.0 * longest if t_max is None else float(t_max)
    if not (t_max > t_min > 0):
        raise ValueError(f"need 0 < t_min < t_max, got {t_min} and {t_max}")

    params = np.concatenate([start, goal, [time_weight, tolerance]])

    def solve_all(N: int, guesses: list, stage: str):
        """Solve every guess (label, T, X, U, Um) on N intervals; the attempts and the
        solutions as (ok, cost, label, status, z, nlp), cheapest converged first."""
        nlp = _Transcription(f, r, n, m, N, wrap, weights, mode, goal_distance,
                             max_iter, ipopt)
        lbx = np.full(nlp.n_vars, -np.inf)
        ubx = np.full(nlp.n_vars, np.inf)
        lbx[0], ubx[0] = t_min, t_max
        lbx[nlp.ix:nlp.iu] = np.tile(x_low, N + 1)
        ubx[nlp.ix:nlp.iu] = np.tile(x_high, N + 1)
        lbx[nlp.iu:nlp.id] = np.tile(u_low, 2 * N + 1)
        ubx[nlp.iu:nlp.id] = np.tile(u_high, 2 * N + 1)
        lbx[nlp.id:], ubx[nlp.id:] = -np.pi, np.pi
        if mode == "point":  # a point in the weighted angles (free where the weight is 0)
            for k, j in enumerate(wrap):
                if weights[j] > 0:
                    lbx[nlp.id + k] = ubx[nlp.id + k] = 0.0
        attempts, solutions = [], []
        for label, T0, X0, U0, Um0 in guesses:
            D0 = np.array([(X0[-1, j] - goal[j] + np.pi) % (2 * np.pi) - np.pi for j in wrap])
            z0 = nlp.pack(np.clip(T0, t_min, t_max), np.clip(X0, x_low, x_high),
                          np.clip(U0, u_low, u_high), np.clip(Um0, u_low, u_high),
                          np.clip(D0, lbx[nlp.id:], ubx[nlp.id:]))
            c = time.process_time()
            iterations = 0
            first = None
            if fixed_first:  # the guess's duration held first: T cannot collapse
                fixed_lbx, fixed_ubx = lbx.copy(), ubx.copy()
                fixed_lbx[0] = fixed_ubx[0] = z0[0]
                out = nlp.solver(x0=z0, p=params, lbx=fixed_lbx, ubx=fixed_ubx, lbg=nlp.lbg,
                                 ubg=nlp.ubg)
                iterations += int(nlp.solver.stats()["iter_count"])
                first = str(nlp.solver.stats()["return_status"])
                z1 = np.asarray(out["x"], dtype=np.float64).ravel()
                if first in _SUCCESS and np.isfinite(z1).all():
                    z0 = z1
            out = nlp.solver(x0=z0, p=params, lbx=lbx, ubx=ubx, lbg=nlp.lbg, ubg=nlp.ubg)
            stats = nlp.solver.stats()
            iterations += int(stats["iter_count"])
            z = np.asarray(out["x"], dtype=np.float64).ravel()
            cost = float(out["f"])
            status = str(stats["return_status"])
            ok = status in _SUCCESS and math.isfinite(cost) and bool(np.isfinite(z).all())
            attempts.append({"stage": stage, "n_intervals": N, "guess": label,
                             "status": status, "success": ok, "cost": cost,
                             "duration": float(z[0]), "iterations": iterations,
                             "fixed_duration_status": first,
                             "cpu_s": time.process_time() - c})
            solutions.append((ok, cost if math.isfinite(cost) else math.inf, label, status, z,
                              nlp))
        solutions.sort(key=lambda sol: (not sol[0], sol[1]))
        return attempts, solutions

    def initial_guesses(N: int, with_path: bool = True) -> list:
        guesses = []
        if path is not None and with_path:
            guesses.append(("path", *_path_guess(path, N, m, angles)))
        base = goal.copy()
        for j in guess_wrap:  # the representative nearest the start
            base[j] = goal[j] + 2 * np.pi * np.round((start[j] - goal[j]) / (2 * np.pi))
        for combo in itertools.product(turns, repeat=len(guess_wrap)):
            target = base.copy()
            for j, k in zip(guess_wrap, combo, strict=True):
                target[j] += 2 * np.pi * k
            label = "" if not guess_wrap or len(turns) == 1 else f" turns={combo}"
            for d in durations:
                guesses.append((f"line T={d:g}{label}", *_line_guess(start, target, d, N, m)))
        return guesses

    guess_wrap = wrap if mode != "task" else angles
    if search_intervals is None or int(search_intervals) == n_intervals:
        attempts, solutions = solve_all(n_intervals, initial_guesses(n_intervals), "search")
    else:
        # the lines on the coarse grid; a given path is already a good guess: fine grid
        attempts, coarse = solve_all(int(search_intervals),
                                     initial_guesses(int(search_intervals), False), "search")
        refine = []
        for ok, cost, label, _, z, nlp in coarse:
            if ok and len(refine) < refine_best and all(
                    abs(cost - c) > 1e-6 * abs(c) for c, _ in refine):
                refine.append((cost, (label, z, nlp)))
        if not refine:  # nothing converged: the search's best attempt, refined anyway
            refine = [(coarse[0][1], (coarse[0][2], coarse[0][4], coarse[0][5]))]
        fine = [] if path is None else [("path", *_path_guess(path, n_intervals, m, angles))]
        for _, (label, z, nlp) in refine:
            coarse_result = _unpacked_result(nlp, z)
            fine.append((f"{label} (refined)",
                         *_path_guess(coarse_result, n_intervals, m, angles)))
        more, solutions = solve_all(n_intervals, fine, "refine")
        attempts += more
        if not solutions[0][0] and coarse[0][0]:  # no refinement converged: the search's
            solutions = coarse[:1]                # converged best, on its own grid
            solutions[0] = (*solutions[0][:2], f"{solutions[0][2]} (search grid: no "
                            "refinement converged)", *solutions[0][3:])
    ok, cost, label, status, z, nlp = solutions[0]
    N = nlp.N
    T, X, U, Um, _ = nlp.unpack(z)
    result = CollocationResult(
        success=ok, status=status, cost=cost, duration=T, times=np.linspace(0, T, N + 1),
        states=X, controls=U, mid_controls=Um, guess=label, n_intervals=N, cpu_s=0.0,
        attempts=attempts)

    # independent checks on the system's numpy dynamics
    def distance(x):
        if goal_distance is not None:
            return float(goal_distance(x))
        diff = x - goal
        for j in wrap:
            diff[j] = (diff[j] + np.pi) % (2 * np.pi) - np.pi
        return float(np.linalg.norm(weights * diff))

    end = _rk4_resim(system, start, result)
    result.resim_error = float(np.abs(end - X[-1]).max())
    result.interval_error = _interval_error(system, result)
    result.resim_goal_distance = distance(end)
    result.goal_distance = distance(X[-1].copy())
    result.resim_cost = _exact_cost(result, r, time_weight)
    k = max(1, round(T / HELD_DT))
    u_held = result.control_at(T * (np.arange(k) + 0.5) / k)
    held = propagate_controls(system, start, u_held, np.ones(k, dtype=np.int64), T / k)
    result.held_error = float(np.abs(held[-1] - X[-1]).max())
    result.cpu_s = time.process_time() - cpu0
    return result


def problem_optimum(problem, *, time_weight: float = 1.0,
                    goal_distance: Callable[[Any], Any] | None = None,
                    **kwargs: Any) -> CollocationResult:
    """`optimal_cost` for a `PlanningProblem`: its start, goal, tolerance, ``u_max``, state
    constraints, ``wrap_goal`` and ``goal_weights``. A problem with a user goal region
    (``goal_fn``, numpy) needs ``goal_distance``, its CasADi-compatible twin; obstacles are
    not supported. ``kwargs`` go to `optimal_cost` (n_intervals, durations, path, ...)."""
    if problem.validity:
        raise ValueError("the collocation does not handle obstacles or validity checkers")
    if problem.goal_fn is not None and goal_distance is None:
        raise ValueError("the problem has a user goal region (goal_fn, numpy): pass its "
                         "CasADi-compatible twin as goal_distance")
    low, high = problem.constraint_box
    return optimal_cost(
        problem.system, problem.start, problem.goal, tolerance=problem.goal_tolerance,
        time_weight=time_weight, u_max=problem.u_max, state_low=list(low),
        state_high=list(high), wrap_goal=problem.wrap_goal,
        goal_weights=problem.goal_weights, goal_distance=goal_distance, **kwargs)
