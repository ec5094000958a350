"""The package's one RK4 family.

- The compiled kernels of the state+costate(+cost) ODEs (``rollout``, ``rollout_batch``):
  ``z = (x, lambda, cost)`` of length ``2n+1``; ``rhs(z, w, out)`` is the system's compiled
  right-hand side, writing the state+costate derivative and the running cost (last entry).
  Batched rollouts stop per row (paper Experiments: when the cost exceeds a bound or the state
  leaves a ball around its start), so no row costs more steps than it needs.
- `propagate` / `propagate_controls`: the plain dynamics ``x' = f(x, u)`` under constant /
  piecewise-constant inputs (``propagate_jit``); RRT-CoLearn's random-control edges and every
  peer (random-control RRT, OMPL's planners, the direct method) execute and re-simulate their
  paths with them.
- `rk4_step`: the same step in numpy for any vector field, the reference the kernels are
  checked against and the fallback for a system without compiled kernels.

numba can neither cache a function that receives another compiled function as an argument
nor one that closes over it, so the kernels are kept as source and compiled into each system
module's namespace by `define_kernels`, where they call that module's globals ``rhs`` and
``input_max_abs(z)`` (the largest |u*_i| at ``z``).
"""

from __future__ import annotations

import numpy as np

KERNELS = '''
import math as _math

import numba as _numba
import numpy as _np


@_numba.njit(cache=True)
def _rk4_step(z, w, dt, k1, k2, k3, k4, tmp, out):
    d = z.shape[0]
    rhs(z, w, k1)
    for i in range(d):
        tmp[i] = z[i] + 0.5 * dt * k1[i]
    rhs(tmp, w, k2)
    for i in range(d):
        tmp[i] = z[i] + 0.5 * dt * k2[i]
    rhs(tmp, w, k3)
    for i in range(d):
        tmp[i] = z[i] + dt * k3[i]
    rhs(tmp, w, k4)
    for i in range(d):
        out[i] = z[i] + dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@_numba.njit(cache=True)
def _rk4_plain_step(x, u, dt, k1, k2, k3, k4, tmp, out):
    # one RK4 step of x' = f(x, u) under the held input u (dynamics_jit) into out
    n = x.shape[0]
    dynamics_jit(x, u, k1)
    for i in range(n):
        tmp[i] = x[i] + 0.5 * dt * k1[i]
    dynamics_jit(tmp, u, k2)
    for i in range(n):
        tmp[i] = x[i] + 0.5 * dt * k2[i]
    dynamics_jit(tmp, u, k3)
    for i in range(n):
        tmp[i] = x[i] + dt * k3[i]
    dynamics_jit(tmp, u, k4)
    for i in range(n):
        out[i] = x[i] + dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@_numba.njit(cache=True)
def rollout_jit(z0, w, dt, n_steps):
    d = z0.shape[0]
    traj = _np.empty((n_steps + 1, d))
    traj[0] = z0
    k1 = _np.empty(d)
    k2 = _np.empty(d)
    k3 = _np.empty(d)
    k4 = _np.empty(d)
    tmp = _np.empty(d)
    for s in range(n_steps):
        _rk4_step(traj[s], w, dt, k1, k2, k3, k4, tmp, traj[s + 1])
    return traj


@_numba.njit(cache=True)
def rollout_batch_jit(z0, w, dt, max_steps, max_cost, max_dist, n, u_max, scale=None,
                      store=0):
    n_sims, d = z0.shape
    keep = n if store == 0 else store
    states = _np.empty((n_sims, max_steps, keep))
    costs = _np.empty((n_sims, max_steps))
    lengths = _np.zeros(n_sims, dtype=_np.int64)
    nonfinite = _np.zeros(n_sims, dtype=_np.bool_)
    k1 = _np.empty(d)
    k2 = _np.empty(d)
    k3 = _np.empty(d)
    k4 = _np.empty(d)
    tmp = _np.empty(d)
    z = _np.empty(d)
    znew = _np.empty(d)
    sc = _np.ones(n)
    if scale is not None:
        sc = scale
    for i in range(n_sims):
        z[:] = z0[i]
        if u_max > 0.0 and input_max_abs(z) > u_max:
            continue
        for s in range(max_steps):
            _rk4_step(z, w, dt, k1, k2, k3, k4, tmp, znew)
            ok = True
            dist2 = 0.0
            for j in range(n):
                dx = (znew[j] - z0[i, j]) * sc[j]
                dist2 += dx * dx
            for j in range(d):
                if not _math.isfinite(znew[j]):
                    ok = False
            if not ok:
                nonfinite[i] = True
                break
            if abs(znew[d - 1]) > max_cost or dist2 > max_dist * max_dist:
                break
            if u_max > 0.0 and input_max_abs(znew) > u_max:
                break
            for j in range(keep):
                states[i, s, j] = znew[j]
            costs[i, s] = znew[d - 1]
            lengths[i] = s + 1
            z[:] = znew
    return states, costs, lengths, nonfinite


@_numba.njit(cache=True)
def _hold(x0, u, length, dt, low, high, out, row, k1, k2, k3, k4, tmp):
    # RK4 of x' = f(x, u) from x0 under the held input u for up to length steps into
    # out[row], out[row + 1], ..., stopped after the first state outside [low, high] or not
    # finite (that state written too): (states inside, stop: 0 none, 1 outside, 2 not
    # finite). The one integration of a random-control draw (propagate_jit, explore_jit)
    n = x0.shape[0]
    x = x0
    for s in range(length):
        _rk4_plain_step(x, u, dt, k1, k2, k3, k4, tmp, out[row + s])
        inside = True
        finite = True
        for i in range(n):
            v = out[row + s, i]
            inside = inside and low[i] <= v <= high[i]
            finite = finite and _math.isfinite(v)
        if not inside:
            return s, 1 if finite else 2
        x = out[row + s]
    return length, 0


@_numba.njit(cache=True)
def hold_jit(x0, u, length, dt, box, out, scratch):
    # _hold for a caller that keeps its own buffers (an OMPL propagator called for every
    # step of every edge): box (2, n) the low and high, scratch (5, n), the states into
    # out[0 :]; returns (states inside, stop) and nothing to box but two integers
    return _hold(x0, u, length, dt, box[0], box[1], out, 0, scratch[0], scratch[1],
                 scratch[2], scratch[3], scratch[4])


@_numba.njit(cache=True)
def propagate_jit(x0, inputs, lengths, dt, low, high, chain):
    # RK4 of x' = f(x, u) from x0 under each constant input inputs[c] held for lengths[c]
    # steps, each draw stopping after its first state outside [low, high] or not finite
    # (that state included): the states after x0, draw after draw (total, n), how many
    # each draw has (c,), and how each stopped (c,): 0 inside throughout, 1 at a state
    # outside, 2 at a state not finite. With chain, each draw starts where the one before
    # it ended (piecewise-constant controls) and a stop ends them all
    n = x0.shape[0]
    c = inputs.shape[0]
    states = _np.empty((lengths.sum(), n))
    counts = _np.zeros(c, _np.int64)
    stops = _np.zeros(c, _np.int64)
    k1 = _np.empty(n)
    k2 = _np.empty(n)
    k3 = _np.empty(n)
    k4 = _np.empty(n)
    tmp = _np.empty(n)
    r = 0
    for j in range(c):
        start = states[r - 1] if chain and r > 0 else x0
        kept, stops[j] = _hold(start, inputs[j], lengths[j], dt, low, high, states, r, k1,
                               k2, k3, k4, tmp)
        counts[j] = kept + (1 if stops[j] > 0 else 0)
        r += counts[j]
        if chain and stops[j] > 0:
            break
    return states[:r], counts, stops


@_numba.njit(cache=True)
def closed_loop_jit(x0, x_e, u_e, K, k, P, u_low, u_high, wrap, dt, max_steps, low, high):
    # the goal connections' loops (planning/lqr.py): u = clip(u_e - K[t] e - k[t], u_low,
    # u_high) held for the RK4 step s, t = min(s, T - 1) (K (T, m, n), k (T, m): the LQR
    # connection's constant gain has T = 1, the finite-horizon law's a gain per step),
    # e = x - x_e with the coordinates where wrap is true modulo a turn. It stops after
    # max_steps steps (how = 0), before the first state outside [low, high] or not finite
    # (1), or after the first state whose value e'Pe exceeds the start's (2; never with
    # P = 0): (states (k + 1, n), inputs (k, m), how)
    n = x0.shape[0]
    m = u_e.shape[0]
    states = _np.empty((max_steps + 1, n))
    inputs = _np.empty((max_steps, m))
    states[0] = x0
    e = _np.empty(n)
    u = _np.empty(m)
    k1 = _np.empty(n)
    k2 = _np.empty(n)
    k3 = _np.empty(n)
    k4 = _np.empty(n)
    tmp = _np.empty(n)
    two_pi = 2.0 * _math.pi
    v0 = 0.0
    for s in range(max_steps + 1):
        x = states[s]
        for i in range(n):
            e[i] = x[i] - x_e[i]
            if wrap[i]:
                e[i] = _np.mod(e[i] + _math.pi, two_pi) - _math.pi
        v = 0.0
        for i in range(n):
            row = 0.0
            for j in range(n):
                row += P[i, j] * e[j]
            v += e[i] * row
        if s == 0:
            v0 = v
        elif v > v0:
            return states[: s + 1], inputs[:s], 2
        if s == max_steps:
            break
        t = min(s, K.shape[0] - 1)
        for i in range(m):
            acc = u_e[i] - k[t, i]
            for j in range(n):
                acc -= K[t, i, j] * e[j]
            u[i] = min(max(acc, u_low[i]), u_high[i])
        _rk4_plain_step(x, u, dt, k1, k2, k3, k4, tmp, states[s + 1])
        inside = True
        for i in range(n):
            inside = inside and low[i] <= states[s + 1, i] <= high[i]
        if not inside:
            return states[: s + 1], inputs[:s], 1
        inputs[s] = u
    return states, inputs, 0



@_numba.njit(cache=True)
def rollout_draws_jit(x0, lams, steps, w, dt, low, high, u_max):
    # the learned steering's draws from x0 (planning/propagator.py, extremal_edges):
    # z = (x0, lams[c], 0) integrated for steps[c] RK4 steps as rollout_jit does, draw after
    # draw into one array (starts (c + 1,) its rows), with |u*| at every row (input_max_abs)
    # and a code per draw: 0 kept, 1 a state outside [low, high], 2 a value not finite (each
    # stops the draw there), 3 |u*| above u_max (> 0) at its start (not integrated)
    c_count, n = lams.shape
    d = 2 * n + 1
    total = 0
    for c in range(c_count):
        total += steps[c] + 1
    traj = _np.empty((total, d))
    u_all = _np.zeros(total)
    starts = _np.empty(c_count + 1, _np.int64)
    codes = _np.zeros(c_count, _np.int64)
    k1 = _np.empty(d)
    k2 = _np.empty(d)
    k3 = _np.empty(d)
    k4 = _np.empty(d)
    tmp = _np.empty(d)
    r = 0
    for c in range(c_count):
        starts[c] = r
        for i in range(n):
            traj[r, i] = x0[i]
            traj[r, n + i] = lams[c, i]
        traj[r, 2 * n] = 0.0
        if u_max > 0.0 and input_max_abs(traj[r]) > u_max:
            codes[c] = 3
            continue
        m = steps[c]
        for s in range(m):
            _rk4_step(traj[r + s], w, dt, k1, k2, k3, k4, tmp, traj[r + s + 1])
            for i in range(n):
                v = traj[r + s + 1, i]
                if not (v >= low[i] and v <= high[i]):
                    codes[c] = 1
            for i in range(d):
                if not _math.isfinite(traj[r + s + 1, i]):
                    codes[c] = 2
            if codes[c] != 0:  # rejected: the rest is not integrated
                break
        if codes[c] == 0:
            for s in range(m + 1):
                u_all[r + s] = input_max_abs(traj[r + s])
        r += m + 1
    starts[c_count] = r
    return traj[:r], u_all[:r], starts, codes


@_numba.njit(cache=True)
def _explore_draw(x0, u, length, dt, traj, row, boxes, k1, k2, k3, k4, tmp):
    # _hold within the constraint box (boxes rows 2, 3) into traj[row + 1 :], with x0 at
    # row: (states kept, stop)
    for i in range(x0.shape[0]):
        traj[row, i] = x0[i]
    return _hold(traj[row], u, length, dt, boxes[2], boxes[3], traj, row + 1, k1, k2, k3, k4,
                 tmp)


@_numba.njit(cache=True, inline="always")
def _mod(a, p):
    # numpy's mod(a, p) for p > 0, without fmod where a already lies in (0, p) (there mod
    # returns a itself): the same bits, several times faster in the planner's scans
    if 0.0 < a < p:
        return a
    return _np.mod(a, p)


@_numba.njit(cache=True)
def _ball_d2(x, goal):
    # squared weighted distance of x to the goal ball's centre, angles the short way round
    # (planning/controls.py _pick_state)
    d2 = 0.0
    for i in range(x.shape[0]):
        v = x[i] - goal[0, i]
        if goal[2, i] > 0.0:
            v = _mod(v + _np.pi, 2.0 * _np.pi) - _np.pi
        v *= goal[1, i]
        d2 += v * v
    return d2


@_numba.njit(cache=True)
def _index_point(x, index_consts, ii, out):
    # x in node index ii's stored coordinates (planning/nearest.py NodeIndex._wrapped)
    for j in range(x.shape[0]):
        y = x[j] * index_consts[ii, 0, j] - index_consts[ii, 1, j]
        if index_consts[ii, 3, j] > 0.0:
            y = _mod(y, index_consts[ii, 2, j])
            if y >= index_consts[ii, 2, j]:
                y = 0.0
        out[j] = y


@_numba.njit(cache=True)
def explore_jit(rng, ints, floats, boxes, goal, index_consts, points0, points1, states,
                parents, controls, durations, costs, max_abs_u, shifts, R):
    # the planner's random-control expansions compiled (planning/controls.py,
    # RandomControls.run_batch), with the numbers of the Python iterations (the same generator
    # calls in the same order, the same arithmetic). First, with directed >= 0, a goal-biased
    # iteration's expansion from node directed: `samples` draws. Then up to budget
    # iterations, stopped before a goal-biased one: each draws the goal bias, a uniform
    # target and its nearest node (node index nearest_of, angles modulo a turn), and expands
    # it by one draw. A draw is an input uniform in the input box held for 1..longest steps,
    # stopped before its first state outside the constraint box or not finite; the node
    # goes at the draws' first state in the goal ball (ball), else with one draw at its last
    # state, else at the state nearest the ball's centre (control_edge, _pick_state).
    # ints: budget, iterations, last_growth, stall, longest, ball, n_index, nearest_of, size,
    # directed, samples
    # floats: dt, goal_bias, tol2, w
    # boxes (8, n): sample low/high, constraint low/high, input low/high (first m
    # columns), the shift's low, angle coordinates (1.0) for the shift
    # goal (3, n): goal, weights, angle coordinates (1.0) of the ball test
    # index_consts (2, 4, n): per node index its weight, low, period, angle mask (1.0)
    # Returns (code: 0 budget spent, 1 stopped before a goal-biased iteration (its goal
    # bias drawn), 2 stalled, 3 a node in the goal ball; iterations, nodes, the new edges'
    # states (each from its parent's), their first rows, each new node's iteration and
    # distance to the goal ball's centre, and per action (the directed expansion, then
    # each iteration) 0 a node added, its stop reason (1, 2) or 3 goal-biased)
    budget, iterations, last_growth, stall, longest, ball, n_index, nearest_of, size = \
        ints[0], ints[1], ints[2], ints[3], ints[4], ints[5], ints[6], ints[7], ints[8]
    directed, samples = ints[9], ints[10]
    dt, goal_bias, tol2, w = floats[0], floats[1], floats[2], floats[3]
    n = states.shape[1]
    m = controls.shape[1]
    k1 = _np.empty(n)
    k2 = _np.empty(n)
    k3 = _np.empty(n)
    k4 = _np.empty(n)
    tmp = _np.empty(n)
    q = _np.empty(n)
    inputs = _np.empty((max(samples, 1), m))
    lengths = _np.empty(max(samples, 1), _np.int64)
    actions = budget + 1
    traj = _np.empty((max(16, 4 * (longest + 1)), n))
    used = 0
    starts = _np.empty(actions + 1, _np.int64)
    node_it = _np.empty(actions, _np.int64)
    ends = _np.empty(actions)
    reasons = _np.zeros(actions, _np.int64)
    node = size
    code = 0
    done = 0  # actions taken
    loops = 0  # iterations begun
    pts = points1 if nearest_of == 1 else points0
    while True:
        if directed >= 0:  # the goal-biased iteration's expansion, before the loop
            parent = directed
            count = samples
            directed = -1
        else:
            if loops >= budget:
                break
            loops += 1
            if stall > 0 and iterations - last_growth >= stall:
                code = 2
                break
            iterations += 1
            if rng.random() < goal_bias:
                code = 1
                reasons[done] = 3
                done += 1
                break
            # target uniform in the sampling box, in the node index's coordinates
            for j in range(n):
                q[j] = boxes[0, j] + (boxes[1, j] - boxes[0, j]) * rng.random()
            _index_point(q, index_consts, nearest_of, q)  # (in place: entry by entry)
            parent = 0
            best = 0.0
            for r in range(node):
                acc = 0.0
                for j in range(n):
                    d = pts[r, j] - q[j]
                    p = index_consts[nearest_of, 2, j]
                    if p > 0.0:
                        d = _mod(d + 0.5 * p, p) - 0.5 * p
                    acc += d * d
                if r == 0 or acc < best:
                    parent, best = r, acc
            count = 1
        # the draws: inputs, then lengths (the generator calls of control_edge)
        for c in range(count):
            for i in range(m):
                inputs[c, i] = boxes[4, i] + (boxes[5, i] - boxes[4, i]) * rng.random()
        total = 0
        for c in range(count):
            lengths[c] = rng.integers(1, longest + 1)
            total += lengths[c] + 1
        while used + total > traj.shape[0]:
            grown = _np.empty((2 * traj.shape[0], n))
            grown[:used] = traj[:used]
            traj = grown
        # each draw at its own rows after `used`; the chosen one is moved to `used`
        hit = False
        best_row, best_k, best_d2, best_c = -1, 0, _np.inf, -1
        first_stop = 0
        row = used
        for c in range(count):
            kept, stop = _explore_draw(states[parent], inputs[c], lengths[c], dt, traj, row,
                                       boxes, k1, k2, k3, k4, tmp)
            if c == 0:
                first_stop = stop
            for k in range(kept):
                d2 = _ball_d2(traj[row + 1 + k], goal) if ball else 0.0
                if ball and d2 <= tol2:
                    hit = True
                    best_row, best_k, best_d2, best_c = row, k, d2, c
                    break
                if count == 1 or _math.sqrt(d2) < _math.sqrt(best_d2):
                    best_row, best_k, best_d2, best_c = row, k, d2, c
            if hit:
                break
            row += lengths[c] + 1
        if best_c < 0:  # no draw kept a state: the first says why
            reasons[done] = first_stop
            done += 1
            continue
        kept = best_k + 1
        if best_row != used:
            for r in range(kept + 1):
                traj[used + r] = traj[best_row + r]
        # the node at traj[used + kept], from parent under the chosen input
        x = traj[used + kept]
        u = inputs[best_c]
        uru = 0.0
        uabs = 0.0
        for j in range(m):
            acc = 0.0
            for i in range(m):
                acc += u[i] * R[i, j]
            uru += acc * u[j]
            uabs = max(uabs, abs(u[j]))
        states[node] = x
        parents[node] = parent
        controls[node] = u
        durations[node] = kept * dt
        costs[node] = kept * dt * (w + 0.5 * uru)
        max_abs_u[node] = uabs
        _index_point(x, index_consts, 0, points0[node])
        if n_index == 2:
            _index_point(x, index_consts, 1, points1[node])
        for j in range(n):
            shifts[node, j] = 0.0
            if boxes[7, j] > 0.0:
                shifts[node, j] = -2.0 * _np.pi * _np.floor((x[j] - boxes[6, j])
                                                            / (2.0 * _np.pi))
        k = node - size
        starts[k] = used
        node_it[k] = iterations
        ends[k] = _math.sqrt(best_d2)
        reasons[done] = 0
        done += 1
        used += kept + 1
        node += 1
        last_growth = iterations
        if hit:
            code = 3
            break
    starts[node - size] = used
    k = node - size
    return (code, iterations, node, traj[:used].copy(), starts[: k + 1].copy(),
            node_it[:k].copy(), ends[:k].copy(), reasons[:done].copy())
'''


def define_kernels(namespace: dict) -> None:
    """Compile ``rollout_jit``, ``rollout_batch_jit``, ``propagate_jit``, ``hold_jit``,
    ``closed_loop_jit``, ``rollout_draws_jit`` and ``explore_jit`` into a system module's
    namespace.

    The module must define compiled ``rhs(z, w, out)``, ``input_max_abs(z)`` and
    ``dynamics_jit(x, u, out)`` first.
    """
    exec(compile(KERNELS, namespace["__file__"], "exec"), namespace)


def rollout(system, z0: np.ndarray, w: float, dt: float, n_steps: int) -> np.ndarray:
    """Integrate one ``z0`` (2n+1,) for ``n_steps`` RK4 steps; returns (n_steps+1, 2n+1)."""
    return system.rollout_jit(np.ascontiguousarray(z0, dtype=np.float64), float(w), float(dt),
                              int(n_steps))


def rk4_step(f, x: np.ndarray, dt: float) -> np.ndarray:
    """One classical RK4 step of ``x' = f(x)`` for numpy states (any shape ``f`` accepts):
    the reference the compiled kernels are checked against (`rrtcolearn.systems.check`) and
    the fallback of `propagate` for a system without a compiled ``propagate_jit``."""
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rollout_draws(system, x0: np.ndarray, lams: np.ndarray, steps: np.ndarray, w: float,
                  dt: float, low: np.ndarray, high: np.ndarray, u_max: float | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The state+costate+cost extremals from ``x0`` (n,) with the costates ``lams`` (c, n),
    each for ``steps[c]`` RK4 steps (`rollout`), in one array: (rows (total, 2n+1), the
    largest |u*_i| at each row, each draw's first row (c + 1,), a code per draw: 0 kept, 1
    a state after the start outside ``low``/``high``, 2 a value not finite (the first such
    state decides, and the draw is not integrated beyond it), 3 |u*| above ``u_max`` at the
    start, not integrated). One compiled call for a planner's batch of draws."""
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    lams = np.ascontiguousarray(lams, dtype=np.float64)
    steps = np.ascontiguousarray(steps, dtype=np.int64)
    limit = -1.0 if u_max is None else float(u_max)
    if system.rollout_draws_jit is not None:
        return system.rollout_draws_jit(x0, lams, steps, float(w), float(dt), low, high, limit)
    n = len(x0)  # a System built by hand: the same, draw by draw
    parts, u_parts = [], []
    starts, codes = np.zeros(len(lams) + 1, np.int64), np.zeros(len(lams), np.int64)
    for c, (lam, m) in enumerate(zip(lams, steps, strict=True)):
        z0 = np.concatenate([x0, lam, [0.0]])
        if limit > 0.0 and system.input_max_abs_jit(z0) > limit:
            codes[c], traj = 3, z0[None]
        else:
            traj = rollout(system, z0, w, dt, int(m))
            bad = ~(np.all((traj[1:, :n] >= low) & (traj[1:, :n] <= high), axis=1)
                    & np.isfinite(traj[1:]).all(axis=1))
            if bad.any():  # the first such state decides, as the compiled loop stops there
                codes[c] = 1 if np.isfinite(traj[1 + int(np.argmax(bad))]).all() else 2
        u = np.zeros(len(traj))
        if codes[c] == 0:
            u = np.array([system.input_max_abs_jit(z) for z in traj])
        if codes[c] != 3:
            parts.append(traj)
            u_parts.append(u)
        starts[c + 1] = starts[c] + (len(traj) if codes[c] != 3 else 0)
    d = 2 * n + 1
    return (np.concatenate(parts) if parts else np.empty((0, d)),
            np.concatenate(u_parts) if u_parts else np.empty(0), starts, codes)


def propagate_draws(system, x0: np.ndarray, inputs: np.ndarray, lengths: np.ndarray,
                    dt: float, low: np.ndarray, high: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RK4 of the plain dynamics from ``x0`` (n,) under each constant input ``inputs[c]``
    (c, m) held for ``lengths[c]`` steps of ``dt``, each draw stopping after its first state
    outside ``low``/``high`` (n,) (+-inf where free) or not finite, that state included.
    Returns the states after ``x0``, draw after draw (total, n), the number of each draw's
    states (c,) and how each stopped (c,): 0 inside throughout, 1 at a state outside, 2 at
    a state not finite. One compiled call for a planner's whole batch of control draws."""
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    inputs = np.ascontiguousarray(inputs, dtype=np.float64)
    lengths = np.ascontiguousarray(lengths, dtype=np.int64)
    if system.propagate_jit is not None:
        return system.propagate_jit(x0, inputs, lengths, float(dt), low, high, False)
    n, parts = len(x0), []  # a System built by hand, without compiled kernels
    counts, stops = np.zeros(len(inputs), np.int64), np.zeros(len(inputs), np.int64)
    for c, (u, steps) in enumerate(zip(inputs, lengths, strict=True)):
        x, f = x0[None], (lambda y, ub=u[None]: system.dynamics(y, ub))
        for _ in range(int(steps)):
            x = rk4_step(f, x, dt)
            parts.append(x)
            counts[c] += 1
            if not np.all((low <= x) & (x <= high)):
                stops[c] = 1 if np.isfinite(x).all() else 2
                break
    return (np.concatenate(parts) if parts else np.empty((0, n))), counts, stops


def propagate(system, x0: np.ndarray, u: np.ndarray, dt: float, n_steps: int,
              low: np.ndarray | None = None, high: np.ndarray | None = None) -> np.ndarray:
    """RK4 of the plain dynamics from ``x0`` (n,) under the constant input ``u`` (m,) for
    ``n_steps`` steps of ``dt``: states (n_steps+1, n). With ``low``/``high`` (n,) (+-inf
    where free) it stops early, after the first state outside them or not finite (that state
    is the last row). Piecewise-constant controls (random-control edges, peers' paths) are
    integrated with this one function (`propagate_controls`), a batch of draws with
    `propagate_draws`."""
    n = len(x0)
    low = np.full(n, -np.inf) if low is None else np.ascontiguousarray(low, dtype=np.float64)
    high = np.full(n, np.inf) if high is None else np.ascontiguousarray(high, dtype=np.float64)
    x0 = np.asarray(x0, dtype=np.float64)
    states = propagate_draws(system, x0, np.asarray(u, dtype=np.float64)[None],
                             np.array([int(n_steps)]), dt, low, high)[0]
    return np.concatenate([x0[None], states])


def propagate_controls(system, x0: np.ndarray, controls: np.ndarray, steps: np.ndarray,
                       dt: float, low: np.ndarray | None = None,
                       high: np.ndarray | None = None) -> np.ndarray:
    """`propagate` along piecewise-constant controls: ``controls[k]`` (m,) held for
    ``steps[k]`` RK4 steps of ``dt``, from ``x0`` (n,). Returns the states (1 + sum(steps),
    n) at every step, or fewer when ``low``/``high`` stop it (the first state outside them
    is the last row). Every peer's path is executed and re-simulated with this."""
    controls = np.asarray(controls, dtype=np.float64).reshape(len(steps), -1)
    if system.propagate_jit is not None:  # one compiled call, the controls chained
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        n = len(x0)
        lo = np.full(n, -np.inf) if low is None else np.ascontiguousarray(low, dtype=np.float64)
        hi = np.full(n, np.inf) if high is None else np.ascontiguousarray(high, dtype=np.float64)
        states = system.propagate_jit(x0, np.ascontiguousarray(controls),
                                      np.ascontiguousarray(steps, dtype=np.int64), float(dt),
                                      lo, hi, True)[0]
        return np.concatenate([x0[None], states])
    parts = [np.asarray(x0, dtype=np.float64)[None]]
    x = parts[0][0]
    for u, k in zip(controls, steps, strict=True):
        traj = propagate(system, x, u, dt, int(k), low, high)
        parts.append(traj[1:])
        x = traj[-1]
        if len(traj) < int(k) + 1:
            break
    return np.concatenate(parts)


def rollout_batch(
    system,
    z0: np.ndarray,
    w: float,
    dt: float,
    max_steps: int,
    max_cost: float,
    max_dist: float,
    n: int,
    u_max: float | None = None,
    scale: np.ndarray | None = None,
    with_costate: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Integrate rows of ``z0`` (S, 2n+1) until each stops.

    A negative ``dt`` integrates backwards in time (the cost then decreases from 0).
    A row stops before the first step whose |cost| exceeds ``max_cost``, whose state is farther
    than ``max_dist`` from its start (distance weighted by ``scale`` (n,), default
    ``system.metric_scale``), that is not finite, or (when ``u_max`` is given) whose
    optimal input exceeds ``u_max`` in magnitude; a row whose input at the start already
    exceeds it yields no points. Returns states (S, max_steps, n) (with ``with_costate``,
    (S, max_steps, 2n): states and costates), costs (S, max_steps),
    lengths (S,) — row i's first ``lengths[i]`` steps are valid data points — and a (S,)
    mask of the rows that stopped because the integration overflowed or produced NaN.
    """
    return system.rollout_batch_jit(
        np.ascontiguousarray(z0, dtype=np.float64), float(w), float(dt), int(max_steps),
        float(max_cost), float(max_dist), int(n),
        float(u_max) if u_max is not None else -1.0,
        np.ascontiguousarray(system.metric_scale if scale is None else scale, dtype=np.float64),
        2 * int(n) if with_costate else 0)
