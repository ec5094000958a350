"""Exact steering by shooting: Newton's method on Pontryagin's two-point boundary value problem.

OMPL's control planners can ``steer(from, to)`` exactly when a system provides it; here any
system can. The unknowns are the initial costate and the duration; the equations are
x(T) = target and H* = 0, so every solution is an extremal of the free-final-time problem,
like every data segment. The learned U gives the first guess. The planner uses it only for
the goal connection (``plan.goal_connect``): the last edge of a learned tree is where k-NN or
a network is least precise, and where precision is all that counts.

Each Newton iteration integrates the guess and two perturbations per costate coordinate in a
single batched RK4 call; the state at a duration between two RK4 steps is interpolated
linearly, so the residual is continuous in T. The result's duration is rounded to the RK4
grid, and the caller checks the edge by integrating it as any other edge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from rrtcolearn.integrate import rollout_batch
from rrtcolearn.systems.base import System

_EPS = 1e-7  # relative finite-difference step of the costate coordinates
_STEP_SIZES = (1.0, 0.5, 0.25, 0.1)  # backtracking line search, evaluated in one batch
_LAND_STEP_SIZES = (1.0, 0.5, 0.25, 0.1, 0.03, 0.01)  # `land`'s
# `multiple_shoot`'s dogleg trust radii, as multiples of the last accepted one (scaled
# variables), tried in one batch
_DOGLEG_RADII = np.array([2.0, 1.0, 0.5, 0.25, 0.1, 0.03, 0.01])
# the first trust radius (scaled units): 10 converged on 5 of 6 first paths (pendulum at
# |u| <= 1, quadrotor; 3 seeds each), 1 on 4, 100 on 4 (docs/anytime.md)
_DOGLEG_START = 10.0


def _norm(a: np.ndarray) -> np.ndarray | float:
    """Euclidean norm along the last axis by elementwise squares and numpy's own sum, not
    BLAS's dot (`np.linalg.norm`): the same bits on every CPU, whatever kernel BLAS picks."""
    with np.errstate(all="ignore"):
        out = np.sqrt(np.sum(a * a, axis=-1))
    return float(out) if out.ndim == 0 else out


@numba.njit(cache=True)
def _eliminate(m, scale):
    """x with a x = b for the augmented matrix ``m`` = [a | b] (n, n + 1), which it
    overwrites: Gaussian elimination with partial pivoting (`np.argmax`'s pivot) and
    back substitution, every operation in the order `_solve`'s numpy version did them;
    (x, True), or (unfinished, False) where a pivot is not above ``1e-13 * scale``."""
    n = m.shape[0]
    x = np.zeros(n)
    for k in range(n):
        p, best = k, abs(m[k, k])
        for i in range(k, n):  # np.argmax's choice: the first NaN, else the first largest
            v = abs(m[i, k])
            if np.isnan(v):
                p = i
                break
            if v > best:
                p, best = i, v
        if not abs(m[p, k]) > 1e-13 * scale:
            return x, False
        if p != k:
            for j in range(n + 1):
                m[k, j], m[p, j] = m[p, j], m[k, j]
        for i in range(k + 1, n):
            f = m[i, k] / m[k, k]
            for j in range(n + 1):
                m[i, j] -= f * m[k, j]
    for k in range(n - 1, -1, -1):
        acc = m[k, n]
        for j in range(k + 1, n):
            acc -= m[k, j] * x[j]
        x[k] = acc / m[k, k]
    return x, True


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a x = b for a small square ``a``: Gaussian elimination with partial pivoting in
    scalar operations (`_eliminate`, compiled), so that a Newton step (and the tree it grows)
    has the same bits on every CPU; LAPACK's least squares (`np.linalg.lstsq`, whose result
    depends on the BLAS kernel the CPU selects) only where a pivot vanishes (``a`` singular
    to working precision)."""
    m = np.hstack([a, b[:, None]]).astype(np.float64, copy=False)
    scale = float(np.max(np.abs(a))) if a.size else 0.0
    x, ok = _eliminate(m, scale)
    return x if ok else np.linalg.lstsq(a, b, rcond=None)[0]


@numba.njit(cache=True)
def _eliminate_sparse(m: np.ndarray, tiny: float) -> bool:
    """`_solve_sparse`'s elimination of ``m`` = [a | b] in place, compiled (scalar loops, no
    BLAS: the same bits on every CPU), skipping the zeros of a sparse ``a``; False where a
    pivot vanishes."""
    n = m.shape[0]
    for k in range(n):
        p, big = k, abs(m[k, k])
        for i in range(k + 1, n):
            if abs(m[i, k]) > big:
                p, big = i, abs(m[i, k])
        if not big > tiny:
            return False
        if p != k:
            for j in range(k, n + 1):
                m[k, j], m[p, j] = m[p, j], m[k, j]
        for i in range(k + 1, n):
            if m[i, k] != 0.0:
                f = m[i, k] / m[k, k]
                for j in range(k, n + 1):
                    if m[k, j] != 0.0:
                        m[i, j] -= f * m[k, j]
    for k in range(n - 1, -1, -1):
        acc = m[k, n]
        for j in range(k + 1, n):
            acc -= m[k, j] * m[j, n]
        m[k, n] = acc / m[k, k]
    return True


def _solve_sparse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`_solve` for `multiple_shoot`'s sparse Jacobians of some hundred unknowns, compiled:
    the same elimination with partial pivoting, zeros skipped; LAPACK's least squares where
    a pivot vanishes."""
    m = np.ascontiguousarray(np.hstack([a, b[:, None]]), dtype=np.float64)
    scale = float(np.max(np.abs(a))) if a.size else 0.0
    if not _eliminate_sparse(m, 1e-13 * scale):
        return np.linalg.lstsq(a, b, rcond=None)[0]
    return m[:, -1].copy()


@dataclass(frozen=True)
class ShootingResult:
    """Steering parameters (k,) and duration (a whole number of RK4 steps) whose edge ends
    ``residual`` away from the target, after ``iterations`` Newton steps."""

    params: np.ndarray
    steps: int
    residual: float
    iterations: int


def endpoints(system: System, x0: np.ndarray, v: np.ndarray, w: float, dt: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """State and costate (B, 2n) at duration v[:, -1] from x0 (n,) or each row's own start
    (B, n) with costates v[:, :-1], interpolated between RK4 steps of signed size ``dt``
    (negative: backwards in time), and their rate of change with the duration (B, 2n); NaN
    rows where the integration fails."""
    n, b = x0.shape[-1], len(v)
    h = abs(dt)
    k = np.floor(v[:, -1] / h).astype(np.int64)
    frac = v[:, -1] / h - k
    z0 = np.empty((b, 2 * n + 1))
    z0[:, :n] = x0
    z0[:, n : 2 * n] = v[:, :-1]
    z0[:, 2 * n] = 0.0
    states, _, lengths, _ = rollout_batch(system, z0, w, dt, int(k.max()) + 1, np.inf,
                                          np.inf, n, with_costate=True)
    return _interpolate(states, z0, k, frac, lengths, h)


@numba.njit(cache=True)
def _interpolate(states, z0, k, frac, lengths, h):
    """`endpoints`' state and costate (B, 2n) and their rate (B, 2n) of its batch
    ``states`` (B, steps, 2n): row i between RK4 step k[i] - 1 (z0 itself for k[i] = 0)
    and k[i], at fraction frac[i]; NaN rows where the row stopped before step k[i]."""
    b, d = states.shape[0], states.shape[2]
    z = np.empty((b, d))
    rate = np.empty((b, d))
    for i in range(b):
        # step s of the batch is the point after s + 1 RK4 steps
        ki = k[i]
        if not lengths[i] >= ki + 1:
            z[i] = np.nan
            rate[i] = np.nan
            continue
        f = frac[i]
        for j in range(d):
            before = states[i, ki - 1, j] if ki >= 1 else z0[i, j]
            after = states[i, ki, j]
            z[i, j] = before + f * (after - before)
            rate[i, j] = (after - before) / h
    return z, rate


def compiled_kernels(system: System) -> list[tuple[Callable, Callable[[], object]]]:
    """This module's compiled functions, each with a call that loads it (numba's cache) with
    the argument types a solve passes, through the function the solver calls it by
    (`planning.rrt.load_kernels`)."""
    n = system.n_states
    x = np.ascontiguousarray((system.state_low + system.state_high) / 2, dtype=np.float64)
    v = np.append(np.zeros(n), 0.01)[None]
    return [(_eliminate, lambda: _solve(np.eye(n + 1), np.ones(n + 1))),
            (_interpolate, lambda: endpoints(system, x, v, 1.0, 0.01)),
            (_eliminate_sparse, lambda: _solve_sparse(np.eye(n + 1), np.ones(n + 1)))]


def _best_descent(residuals: np.ndarray, norm: float) -> tuple[int, float] | None:
    """The line search's pick: the candidate (row of ``residuals``) with the least finite
    residual norm and that norm, or None when none is below ``norm``."""
    with np.errstate(all="ignore"):
        norms = _norm(residuals)
    norms[~np.isfinite(norms)] = np.inf
    best = int(np.argmin(norms))
    if not norms[best] < norm:
        return None
    return best, float(norms[best])


def _hamiltonian(system: System, x0: np.ndarray, lam: np.ndarray, w: float) -> np.ndarray:
    """H*(x0, lambda) (B,) for costates (B, n)."""
    x = np.broadcast_to(x0, lam.shape)
    return system.hamiltonian(x, lam, system.optimal_control(x, lam), w)


def newton(system: System, x0: np.ndarray, lam0: np.ndarray, duration0: float,
           offset: Callable[[np.ndarray], np.ndarray], *, time_weight: float, dt: float,
           max_duration: float, tolerance: float, max_iterations: int = 20
           ) -> tuple[np.ndarray, np.ndarray, float, int] | None:
    """Costate at ``x0`` and duration (n + 1,) whose extremal ends where ``offset`` vanishes.

    Solves offset(x(T)) = 0, H*(x0, lambda0) = 0 for (lambda0, T) by damped Newton steps
    from (``lam0``, ``duration0``), with T kept in [|dt|, max_duration]; a negative ``dt``
    integrates backwards in time, so x0 is then where the extremal ends. Returns the
    solution, the state and costate at the far end (2n,), the state residual and the number
    of iterations, or None when it does not get below ``tolerance`` within
    ``max_iterations``.
    """
    w = float(time_weight)
    n = len(x0)
    h = abs(dt)
    v = np.concatenate([lam0, [float(np.clip(duration0, h, max_duration))]])

    def residual(vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z, rate = endpoints(system, x0, vs, w, dt)
        with np.errstate(all="ignore"):
            hs = _hamiltonian(system, x0, vs[:, :-1], w)
            return np.hstack([offset(z[:, :n]), hs[:, None]]), rate, z

    r, rate, z = (a[0] for a in residual(v[None]))
    norm = _norm(r)
    for it in range(max_iterations + 1):
        if not np.isfinite(norm):
            return None
        state_norm = _norm(r[:n])
        if state_norm <= tolerance and abs(r[n]) <= 1e-9 * (1 + abs(w)):
            return v, z, state_norm, it
        if it == max_iterations:
            return None
        # Jacobian: costates by central differences (relative steps), duration from the
        # state's rate (H* does not depend on it). Forward differences are not enough where
        # the extremals are sensitive: into the acrobot's upright their truncation error
        # made the Newton step no descent direction (docs/method.md)
        eps = _EPS * np.maximum(1.0, np.abs(v[:n]))
        probe = np.repeat(v[None], 2 * n, axis=0)
        probe[np.arange(n), np.arange(n)] += eps
        probe[n + np.arange(n), np.arange(n)] -= eps
        rp, _, _ = residual(probe)
        jac = np.empty((n + 1, n + 1))
        jac[:, :n] = ((rp[:n] - rp[n:]) / (2.0 * eps[:, None])).T
        jac[:n, n] = rate[:n]
        jac[n, n] = 0.0
        if not np.isfinite(jac).all():
            return None
        step = _solve(jac, -r)
        # trust region: the costate may change by at most its size (or 1), the duration by
        # half of itself (or 0.2 s); then a backtracking line search, evaluated in one batch
        shrink = max(1.0, _norm(step[:n])
                     / max(1.0, _norm(v[:n])),
                     abs(step[n]) / max(0.2, 0.5 * v[-1]))
        step = step / shrink
        cand = v[None] + np.asarray(_STEP_SIZES)[:, None] * step[None]
        cand[:, -1] = np.clip(cand[:, -1], h, max_duration)
        rc, ratec, zc = residual(cand)
        found = _best_descent(rc, norm)
        if found is None:
            return None
        best, norm = found
        v, r, rate, z = cand[best], rc[best], ratec[best], zc[best]
    return None


def shoot(system: System, x0: np.ndarray, params0: np.ndarray, duration0: float,
          offset: Callable[[np.ndarray], np.ndarray], *, time_weight: float, dt: float,
          max_duration: float, tolerance: float, max_iterations: int = 20
          ) -> ShootingResult | None:
    """Steering parameters and duration that take ``x0`` (n,) to the target.

    ``offset(states (B, n)) -> (B, n)`` is the state minus the target (angles the short way
    round, if the goal test wraps them). Starts from the costate of ``params0`` (k,) and
    ``duration0`` (the learned U) and solves x(T) = target, H*(x0, lambda0) = 0 for
    (lambda0, T) by `newton`: in costate space the equations are smooth, where a
    parametrisation of the H* = 0 surface has singularities. Stops once the state residual
    is below ``tolerance``; the parameters returned are the system's for the costate found.
    None when it does not get there within ``max_iterations`` or the system cannot map a
    costate back to its parameters.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    lam0, valid = system.costate_from_params(x0[None], np.asarray(params0, dtype=np.float64)[None],
                                             float(time_weight))
    if not valid[0] or system.params_from_costate is None:
        return None
    sol = newton(system, x0, lam0[0], duration0, offset, time_weight=time_weight, dt=dt,
                 max_duration=max_duration, tolerance=tolerance,
                 max_iterations=max_iterations)
    if sol is None:
        return None
    v, _, res, it = sol
    params = system.params_from_costate(x0[None], v[None, :-1])[0]
    return ShootingResult(params, max(1, round(v[-1] / dt)), res, it)


def land(system: System, x0: np.ndarray, lam0: np.ndarray, steps: int, target: np.ndarray, *,
         time_weight: float, dt: float, tolerance: float, max_iterations: int = 12
         ) -> np.ndarray | None:
    """The costate at ``x0`` (n,) whose extremal ends on ``target`` (n,) after exactly
    ``steps`` RK4 steps of ``dt``, by Newton's method on the costate alone from ``lam0``
    (a `shoot` solution, whose duration was rounded to the grid); None unless the state
    residual gets below ``tolerance`` within ``max_iterations``.

    The duration being fixed, H* = 0 is given up: the extremal is Pontryagin's for that
    duration, its H* off zero by about the rounding (`shoot` ends within half a step of its
    target, this one on it, so that what follows it can be simulated again from there)."""
    n = len(x0)
    w = float(time_weight)
    duration = steps * abs(dt)
    lam = np.asarray(lam0, dtype=np.float64).copy()

    def ends(lams: np.ndarray) -> np.ndarray:
        v = np.hstack([lams, np.full((len(lams), 1), duration)])
        return endpoints(system, x0, v, w, dt)[0][:, :n] - target

    r = ends(lam[None])[0]
    for _ in range(max_iterations + 1):
        norm = _norm(r)
        if not np.isfinite(norm):
            return None
        if norm <= tolerance:
            return lam
        eps = _EPS * np.maximum(1.0, np.abs(lam))
        probe = np.repeat(lam[None], 2 * n, axis=0)
        probe[np.arange(n), np.arange(n)] += eps
        probe[n + np.arange(n), np.arange(n)] -= eps
        rp = ends(probe)
        jac = ((rp[:n] - rp[n:]) / (2.0 * eps[:, None])).T
        if not np.isfinite(jac).all():
            return None
        # a backtracking line search in one batch, deeper than `newton`'s, taking the
        # longest step that descends (not the one that descends most): into the shipped
        # acrobot's costates of 1e3 the step that descended most was ever shorter and
        # Newton crawled (on seed 0 of its k-NN model: 2 of 14 converged shots landed, and
        # 10 were lost behind the miss; this way none were lost)
        cand = lam[None] + np.asarray(_LAND_STEP_SIZES)[:, None] * \
            _solve(jac, -r)[None]
        rc = ends(cand)
        with np.errstate(all="ignore"):
            norms = _norm(rc)
        descends = np.flatnonzero(norms < norm)  # NaN rows compare False
        if not descends.size:
            return None
        lam, r = cand[descends[0]], rc[descends[0]]
    return None


@dataclass(frozen=True)
class MultipleShootingResult:
    """One extremal as M segments: each segment's start state (M, n; row 0 the fixed start)
    and costate there (M, n), its duration in RK4 steps (M,), the residual norm of the
    matching conditions and the Newton iterations of each phase (free time, on the grid)."""

    states: np.ndarray
    costates: np.ndarray
    steps: np.ndarray
    residual: float
    iterations: tuple[int, int]


def _ms_newton(system: System, x0: np.ndarray, lams: np.ndarray, states: np.ndarray,
               durations: np.ndarray, terminal: Callable[[np.ndarray], np.ndarray],
               free_time: bool, w: float, dt: float, max_duration: float, tolerance: float,
               max_iterations: int, stop: Callable[[], bool] | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int] | None:
    """`multiple_shoot`'s Newton solve: (costates (M, n), interior states (M - 1, n),
    durations (M,), residual norm, iterations) or None. With ``free_time`` the total
    duration is an unknown (the segments keep their shares of it) and H*(x0, lambda_0) = 0
    a condition; else the durations are fixed."""
    m, n = lams.shape
    h = abs(dt)
    share = durations / durations.sum()
    nl, nx = m * n, (m - 1) * n
    size = nl + nx + int(free_time)
    v = np.concatenate([lams.ravel(), states.ravel(),
                        [float(np.clip(durations.sum(), m * h, max_duration))]
                        if free_time else []])
    rows_c = 2 * n * (m - 1)  # continuity rows, then n terminal rows, then H*
    order = np.concatenate([np.arange(n)] + [np.r_[nl + (i - 1) * n + np.arange(n),
                                                    i * n + np.arange(n)]
                                             for i in range(1, m)]
                           + ([np.array([size - 1])] if free_time else [])).astype(np.int64)

    def unpack(vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        b = len(vs)
        lam = vs[:, :nl].reshape(b, m, n)
        xs = np.concatenate([np.broadcast_to(x0, (b, 1, n)),
                             vs[:, nl : nl + nx].reshape(b, m - 1, n)], axis=1)
        durs = vs[:, -1:] * share[None] if free_time else np.broadcast_to(durations, (b, m))
        return lam, xs, durs

    def ends(xs: np.ndarray, lam: np.ndarray, durs: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        # every segment of every candidate in one batched integration
        z, rate = endpoints(system, xs.reshape(-1, n),
                            np.hstack([lam.reshape(-1, n), durs.reshape(-1, 1)]), w, dt)
        return z, rate

    def residual(vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        b = len(vs)
        lam, xs, durs = unpack(vs)
        z, rate = ends(xs, lam, durs)
        z, rate = z.reshape(b, m, 2 * n), rate.reshape(b, m, 2 * n)
        r = np.empty((b, size))
        with np.errstate(all="ignore"):
            gap = np.concatenate([z[:, :-1, :n] - xs[:, 1:], z[:, :-1, n:] - lam[:, 1:]],
                                 axis=2)
            r[:, :rows_c] = gap.reshape(b, rows_c)
            r[:, rows_c : rows_c + n] = terminal(z[:, -1])
            if free_time:
                r[:, -1] = _hamiltonian(system, x0, lam[:, 0], w)
        return r, z, rate

    r, z, rate = (a[0] for a in residual(v[None]))
    norm = _norm(r)
    radius = _DOGLEG_START
    for it in range(max_iterations + 1):
        if not np.isfinite(norm):
            return None
        if norm <= tolerance:
            lam, xs, durs = unpack(v[None])
            return lam[0], xs[0, 1:], durs[0], norm, it
        if it == max_iterations or (stop is not None and stop()):
            return None
        lam, xs, durs = unpack(v[None])
        lam, xs, durs = lam[0], xs[0], durs[0]
        # the Jacobian by central differences, block by block: segment i's end depends on
        # its own start state (i >= 1) and costate only (and the total duration, through
        # the state's and costate's rate); all probes of all segments in one integration
        el = _EPS * np.maximum(1.0, np.abs(lam))  # (m, n)
        ex = _EPS * np.maximum(1.0, np.abs(xs))
        eye = np.eye(n)
        sign = np.array([1.0, -1.0])[None, :, None, None]
        # costate probes of every segment (m, +-, n, n), then state probes of segments 1..
        lam_p = lam[:, None, None, :] + sign * (el[:, None, :, None] * eye)
        x_p = xs[1:, None, None, :] + sign * (ex[1:, None, :, None] * eye)
        starts = np.concatenate([np.broadcast_to(xs[:, None, None, :], lam_p.shape).reshape(-1, n),
                                 x_p.reshape(-1, n)])
        costs = np.concatenate([lam_p.reshape(-1, n), np.broadcast_to(
            lam[1:, None, None, :], x_p.shape).reshape(-1, n)])
        times = np.concatenate([np.repeat(durs, 2 * n), np.repeat(durs[1:], 2 * n)])
        zp, _ = ends(starts, costs, times)
        zl = zp[: 2 * n * m].reshape(m, 2, n, 2 * n)
        zx = zp[2 * n * m :].reshape(m - 1, 2, n, 2 * n)
        d_lam = (zl[:, 0] - zl[:, 1]) / (2.0 * el[:, :, None])  # (m, n wrt, 2n of z)
        d_x = (zx[:, 0] - zx[:, 1]) / (2.0 * ex[1:, :, None])
        jac = np.zeros((size, size))
        idx = np.arange(n)
        for i in range(m - 1):
            rs = slice(2 * n * i, 2 * n * (i + 1))
            jac[rs, i * n : (i + 1) * n] = d_lam[i].T
            if i >= 1:
                jac[rs, nl + (i - 1) * n : nl + i * n] = d_x[i - 1].T
            jac[2 * n * i + idx, nl + i * n + idx] = -1.0
            jac[2 * n * i + n + idx, (i + 1) * n + idx] = -1.0
        if free_time:
            jac[:rows_c, -1] = (share[:-1, None] * rate[:-1]).ravel()
        # the last segment: the terminal conditions through its end
        ts = slice(rows_c, rows_c + n)
        t = terminal(zl[-1].reshape(2 * n, 2 * n))
        jac[ts, (m - 1) * n : m * n] = ((t[:n] - t[n:]) / (2.0 * el[-1][:, None])).T
        if m >= 2:
            t = terminal(zx[-1].reshape(2 * n, 2 * n))
            jac[ts, nl + (m - 2) * n : nl + (m - 1) * n] = \
                ((t[:n] - t[n:]) / (2.0 * ex[-1][:, None])).T
        if free_time:
            dz = _EPS * max(1.0, float(durs[-1]))
            t = terminal(np.stack([z[-1] + dz * rate[-1], z[-1] - dz * rate[-1]]))
            jac[ts, -1] = share[-1] * (t[0] - t[1]) / (2.0 * dz)
        if free_time:
            probe = lam[0] + np.concatenate([el[0][:, None] * eye, -el[0][:, None] * eye])
            with np.errstate(all="ignore"):
                hs = _hamiltonian(system, x0, probe, w)
            jac[-1, :n] = (hs[:n] - hs[n:]) / (2.0 * el[0])
        if not np.isfinite(jac).all():
            return None
        # the unknowns interleaved (lambda_0, x_1, lambda_1, x_2, ...; T last): the rows of
        # segment i then touch a band of columns, and the sparse elimination stays cheap
        step = np.empty(size)
        step[order] = _solve_sparse(jac[:, order], -r)
        # Powell's dogleg in the unknowns scaled by their size (at least 1): Newton's step
        # where it lies within the trust radius, else the path towards the Cauchy point
        # (steepest descent of |r|^2, a descent direction even where saturated inputs make
        # the Jacobian near singular); several radii in one batch, the best kept, its
        # radius the next one's start. `newton`'s trust region with a line search instead:
        # 2 of 12 first paths converged against 4 (pendulum at |u| <= 1, quadrotor,
        # sparse_rrt acrobot and cart-pole, 3 seeds each; docs/anytime.md)
        d = np.maximum(1.0, np.abs(v))
        js = jac * d[None, :]
        ny = step / d
        g = np.sum(js * r[:, None], axis=0)
        jg = np.sum(js * g[None, :], axis=1)
        with np.errstate(all="ignore"):  # a zero gradient: NaN candidates, rejected below
            cy = -(np.sum(g * g) / np.sum(jg * jg)) * g
        nn, nc = _norm(ny), _norm(cy)
        dd = ny - cy
        aa, bb = np.sum(dd * dd), 2.0 * np.sum(cy * dd)
        radii = radius * _DOGLEG_RADII
        ys = []
        for rad in radii:
            if nn <= rad:
                ys.append(ny)
            elif nc >= rad:
                ys.append(cy * (rad / nc))
            else:  # where the segment from the Cauchy point to Newton's leaves the radius
                cc = np.sum(cy * cy) - rad * rad
                ys.append(cy + (-bb + np.sqrt(bb * bb - 4.0 * aa * cc)) / (2.0 * aa) * dd)
        cand = v[None] + np.array(ys) * d[None]
        if free_time:
            cand[:, -1] = np.clip(cand[:, -1], m * h, max_duration)
        rc, zc, ratec = residual(cand)
        found = _best_descent(rc, norm)
        if found is None:
            return None
        best, norm = found
        v, r, z, rate = cand[best], rc[best], zc[best], ratec[best]
        radius = float(radii[best])
    return None


def multiple_shoot(system: System, x0: np.ndarray, costates: np.ndarray, states: np.ndarray,
                   durations: np.ndarray, terminal: Callable[[np.ndarray], np.ndarray], *,
                   time_weight: float, dt: float, max_duration: float,
                   tolerance: float = 1e-6, grid_tolerance: float = 1e-8,
                   max_iterations: int = 30, stop: Callable[[], bool] | None = None,
                   free_time: bool = True) -> MultipleShootingResult | None:
    """One extremal from ``x0`` (n,) to where ``terminal`` vanishes, by indirect multiple
    shooting over M segments.

    Unknowns: the costate at each segment's start (``costates`` (M, n), the guess), the
    states where segments 1..M-1 start (``states`` (M - 1, n)) and the total duration (the
    segments keep their shares of ``durations`` (M,)). Conditions: state and costate
    continuity where segments meet, ``terminal(z_end (B, 2n)) -> (B, n)`` = 0 at the last
    segment's end (state and costate), and H*(x0, lambda_0) = 0 (free final time; H* is
    constant along an extremal). Newton's method with Powell's dogleg trust region (several
    radii tried in one batch), the Jacobian by central differences in one batched
    integration per iteration. Then the segments' ends are rounded to the RK4 grid and
    the conditions but H* = 0 are solved again with those durations fixed, to
    ``grid_tolerance`` (as
    `land`: H* is then off zero by about the rounding). ``stop()`` is asked before each
    Newton iteration (True: give up). None when either phase fails.

    Without ``free_time`` only the second phase runs, on ``durations`` rounded to whole
    steps: Pontryagin's extremal of that duration (H* off zero). The free phase's segment
    ends move between RK4 steps, where `endpoints` interpolates; along the acrobot's 5-s
    swing-up it stalled at a residual of 7e-5 (no trust radius descends) from the funnel's
    own extremal, where the same segments on the grid, durations fixed, converge in two
    iterations to 1e-13 (docs/anytime.md, "Segments on the RK4 grid")."""
    x0 = np.asarray(x0, dtype=np.float64)
    lams = np.asarray(costates, dtype=np.float64)
    xs = np.asarray(states, dtype=np.float64).reshape(len(lams) - 1, len(x0))
    durs = np.asarray(durations, dtype=np.float64)
    w, h = float(time_weight), abs(dt)
    it1 = 0
    if free_time:
        free = _ms_newton(system, x0, lams, xs, durs, terminal, True, w, dt, max_duration,
                          tolerance, max_iterations, stop)
        if free is None:
            return None
        lams, xs, durs, _, it1 = free
    # the segments' ends rounded to the grid, not each duration: the whole extremal's
    # duration is then off by at most half a step, whatever M (the rounding of M durations
    # added up: 8 segments of 16.5 steps became 8 of 17, H* 12% of w off zero)
    ends = np.rint(np.cumsum(durs) / h)
    steps = np.maximum(1, np.diff(ends, prepend=0.0)).astype(np.int64)
    grid = _ms_newton(system, x0, lams, xs, steps * h, terminal, False, w, dt, max_duration,
                      grid_tolerance, max_iterations, stop)
    if grid is None:
        return None
    lams, xs, _, res, it2 = grid
    return MultipleShootingResult(np.vstack([x0[None], xs]), lams, steps, res, (it1, it2))
