"""Random controls (the expansion of sampling-based kinodynamic planners, OMPL's control RRT
and sparse_rrt's SST): an input uniform in the input box held for a uniform number of steps,
from the node nearest the target; and its compiled batch, which runs the iterations that
are not goal-biased in one call (`integrate.explore_jit`, a measured speed-up). Knows
nothing of the learned functions or the goal connections; a `contracts.Steering`.
"""

from __future__ import annotations

from itertools import pairwise
from typing import NamedTuple

import numba
import numpy as np

from rrtcolearn.integrate import propagate_draws
from rrtcolearn.planning.contracts import Edge, GrowingTree, Progress, grown
from rrtcolearn.planning.propagator import Propagator

# `integrate.propagate_draws`' stop codes as rejection reasons
_STOP_REASONS = np.array([None, "state_box", "nonfinite"], dtype=object)


@numba.njit(cache=True)
def _pick_state(flat, counts, stops, goal, weights, angles, tol2, plain):
    """`RandomControls.control_edge`'s choice among its draws' states, compiled, for a goal
    ball (no user goal function, no obstacles). ``flat`` (total, n) holds every draw's
    states (`integrate.propagate_draws`); a stopped draw's last state is dropped. Returns
    (draw c, its first row in ``flat``, the chosen state's index k within the draw, hit, the
    chosen state's goal distance), or c = -1 (and row 0: the first draw, whose stop says
    why) when no draw kept a state. The choice: the first state in the goal ball, else
    (``plain``) the last state, else the state nearest the goal. Distances as
    `PlanningProblem.goal_distance` computes them (angles of ``angles`` the short way round,
    times ``weights``, Euclidean)."""
    n = goal.shape[0]
    best_c, best_row, best_k, best_d = -1, 0, 0, np.inf
    last_c, last_row, last_k, last_d = -1, 0, 0, np.inf
    row = 0
    for c in range(counts.shape[0]):
        kept = counts[c] - (1 if stops[c] > 0 else 0)
        for k in range(kept):
            d2 = 0.0
            for i in range(n):
                v = flat[row + k, i] - goal[i]
                if angles[i]:
                    v = np.mod(v + np.pi, 2.0 * np.pi) - np.pi
                v *= weights[i]
                d2 += v * v
            if d2 <= tol2:
                return c, row, k, True, np.sqrt(d2)
            d = np.sqrt(d2)
            if d < best_d:
                best_c, best_row, best_k, best_d = c, row, k, d
            last_c, last_row, last_k, last_d = c, row, k, d
        row += counts[c]
    if last_c < 0:  # no draw kept a state: every one is empty, the first says why
        return -1, 0, 0, False, np.inf
    if plain:
        return last_c, last_row, last_k, False, last_d
    return best_c, best_row, best_k, False, best_d




class _ExploreConsts(NamedTuple):
    """What `integrate.explore_jit` takes that does not change during a solve."""

    longest: int  # the most RK4 steps an input is held
    floats: np.ndarray  # dt, goal bias, the goal ball's tolerance squared, time weight
    boxes: np.ndarray  # (8, max(n, m)): the rows `integrate.explore_jit` names
    goal: np.ndarray  # (3, n): the ball's goal, weights and angle coordinates (1.0)
    index_consts: np.ndarray  # (indices, 4, n): each node index's weight, low, period, angles


# the most iterations a compiled batch (`RandomControls.run_batch`) runs before the termination
# condition is asked again: a time limit is overrun by at most that many iterations (about
# 13 ms at the sparse_rrt cart-pole's dearest, 0.2 ms each), while a batch's call costs
# about 30 us (most batches end sooner, at the next goal-biased iteration)
BATCH_ITERATIONS = 64


class RandomControls:
    """Random-control edges from the node nearest the target, and their compiled batch.

    Settings it reads (`settings.PlannerSettings`, "random controls"): ``control_samples``
    (draws of a goal-biased expansion), ``max_duration`` (the longest hold), ``dt``,
    ``goal_bias`` and ``stall_iterations`` (the batch runs the loop's iterations).
    ``batch`` holds the compiled iterations' constants while a solve runs them (None: every
    iteration in Python); ``pending`` the parent of a goal-biased expansion left to the next
    batch (-1: none); ``scale`` the input box the draws come from, as a fraction of the
    control box around its input nearest zero (`draw_box`; 1: the whole box; set by
    `RRTCoLearn.solve`'s ``control_scale``).
    """

    kind = "control"

    def __init__(self, propagator: Propagator):
        self.propagator = propagator
        self.problem, self.settings = propagator.problem, propagator.settings
        self.rejected: str | None = "no_costate"
        self.batch: _ExploreConsts | None = None
        self.pending = -1
        self.scale = 1.0

    @property
    def compiled(self) -> bool:
        """Whether the iterations can run compiled: the system has the kernel and there are
        no obstacles (the validity checker is Python)."""
        return self.problem.system.explore_jit is not None and not self.problem.validity

    def start(self, tree: GrowingTree) -> None:
        """Ready for a new solve on ``tree``: the batch's constants, no pending expansion."""
        self.batch = self.batch_constants(tree)
        self.pending = -1

    def steer(self, rng: np.random.Generator, tree: GrowingTree, target: np.ndarray,
              to_goal: bool) -> tuple[int, Edge | None]:
        """A random-control edge from the node nearest ``target`` (weighted, angles modulo a
        turn), directed when ``to_goal``; a goal-biased expansion is left to the next
        compiled batch (``pending``, ``rejected`` None) where the batch runs."""
        parent = int(tree.wrapped.nearest(target, 1)[0])
        if to_goal and self.batch is not None and self.propagator.ball is not None:
            self.pending, self.rejected = parent, None  # the next compiled batch begins with it
            return parent, None
        return parent, self.control_edge(rng, tree.states[parent], to_goal)

    def control_edge(self, rng: np.random.Generator, x0: np.ndarray, directed: bool):
        """A random-control edge from ``x0`` (the expansion of sampling-based kinodynamic
        planners, OMPL's RRT and sparse_rrt's SST): an input uniform in the control box held
        for a uniform number of steps up to the data's longest segment, cut before its first
        state outside the state constraints or in an obstacle (OMPL's propagateWhileValid)
        and at its first state in the goal region. ``directed`` (goal-biased iterations):
        ``control_samples`` draws, and the one passing nearest the goal region (in the goal
        test's own distance) is kept, cut there (OMPL's directed control sampling), unless a
        draw reaches the region. None when no draw has even one valid step."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        count = max(1, s.control_samples) if directed else 1
        longest = self.longest_hold()
        inputs = rng.uniform(*self.draw_box(), size=(count, sys.n_inputs))
        lengths = rng.integers(1, longest + 1, size=count)
        # one compiled call for every draw; a draw's state outside the constraints (or not
        # finite) is its last, and is dropped
        flat, counts, stops = propagate_draws(sys, x0, inputs, lengths, s.dt, *self.propagator.box)
        if self.propagator.ball is not None and not prob.validity:
            # a goal ball and no obstacles: the choice below in one compiled pass
            c, begin, k, hit, d = _pick_state(flat, counts, stops, *self.propagator.ball,
                                          count == 1)
            if c < 0:
                self.rejected = _STOP_REASONS[stops[begin]]
                return None
            u = inputs[c]
            traj = np.empty((k + 2, x0.size))
            traj[0] = x0
            traj[1:] = flat[begin : begin + k + 1]
            rate = self.propagator.hold_rate(u)
            return Edge(traj, k + 1, (k + 1) * s.dt * rate, float(np.abs(u).max()), hit,
                        control=u, end_distance=float(d))
        reasons = _STOP_REASONS[stops]  # a copy: "obstacle" may replace one below
        if stops.any():
            keep = np.ones(len(flat), bool)
            keep[np.cumsum(counts)[stops > 0] - 1] = False
            flat, counts = flat[keep], counts - (stops > 0)
        if prob.validity and len(flat):  # obstacles need every state: cut each draw there
            ok = prob.validity(flat)
            if not ok.all():
                parts, begin = [], 0
                for c, k in enumerate(counts.tolist()):
                    part = flat[begin : begin + k]
                    begin += k
                    bad = np.flatnonzero(~ok[begin - k : begin])
                    if bad.size:
                        part, reasons[c] = part[: bad[0]], "obstacle"
                    parts.append(part)
                counts = np.array([len(p) for p in parts])
                flat = np.concatenate(parts)
        if not counts.any():
            self.rejected = reasons[int(np.flatnonzero(counts == 0)[0])]
            return None
        ends = np.cumsum(counts)
        # a user's goal function is called once per edge: its distances serve the goal test,
        # the directed choice and the end's distance (the planner's progress)
        dist = prob.goal_distance(flat) if prob.goal_fn is not None else None
        hits = np.flatnonzero(dist <= prob.goal_tolerance if dist is not None
                              else self.propagator.goal_mask(flat))
        hit = bool(hits.size)
        if hit:  # the first draw's first state in the goal region
            j = int(hits[0])
        elif count == 1:  # the plain random control: its whole valid prefix
            j = len(flat) - 1
        else:  # directed: the state nearest the goal region
            j = int(np.argmin(prob.goal_distance(flat) if dist is None else dist))
        c = int(np.searchsorted(ends, j, side="right"))
        begin = int(ends[c - 1]) if c else 0
        k = j - begin
        u = inputs[c]
        traj = np.vstack([x0[None], flat[begin : j + 1]])
        rate = self.propagator.hold_rate(u)
        end_distance = float(dist[j]) if dist is not None else \
            float(prob.goal_distance(traj[-1:])[0])
        return Edge(traj, k + 1, (k + 1) * s.dt * rate, float(np.abs(u).max()), hit,
                    control=u, end_distance=end_distance)

    def run_batch(self, rng: np.random.Generator, tree: GrowingTree, progress: Progress,
                  budget: int) -> bool:
        """Up to ``budget`` of the loop's iterations compiled (`integrate.explore_jit`): the
        random-control iterations that are not goal-biased, exactly as the loop runs them
        (the same draws, nodes and counts), after the directed control expansion of the
        goal-biased iteration before them if `steer` left it here (``pending``). Returns True
        when the last iteration drew the goal bias: its goal target, connections and
        expansion are the loop's to run. Sets ``progress.goal_node`` when a node reached the
        goal region and ``progress.stalled`` when the tree stalled."""
        prob, s, run = self.problem, self.settings, progress
        data, ex, ball = tree.data, self.batch, self.propagator.ball
        size = data.n_nodes
        data.reserve(budget + 1)  # (+ 1: a goal-biased iteration's expansion first)
        points = [index.reserve(budget + 1) for index in tree.indices]
        if tree.shifts.shape[0] < size + budget + 1:
            tree.shifts = grown(tree.shifts, size + budget + 1, 0.0)
        ints = np.array([budget, run.iterations, run.last_growth, s.stall_iterations,
                         ex.longest, ball is not None, len(points),
                         len(points) - 1, size, self.pending, max(1, s.control_samples)],
                        dtype=np.int64)
        self.pending = -1
        code, iterations, nodes, traj, starts, node_it, ends, reasons = \
            prob.system.explore_jit(rng, ints, ex.floats, ex.boxes, ex.goal, ex.index_consts,
                                    points[0], points[-1], data.states, data.parents,
                                    data.controls, data.durations, data.costs,
                                    data.max_abs_u, tree.shifts, self.propagator.input_weight)
        first_it = run.iterations
        run.iterations = int(iterations)
        added = nodes - size
        if added and ball is None:  # the user's goal function on the new states
            code, added, ends = self._deferred_goal(tree, size, added, traj, starts, code)
            if code == 3:  # the batch ends at that edge's iteration
                run.iterations = int(node_it[added - 1])
                reasons = reasons[: run.iterations - first_it]
        run.since_growth_nearer += run.iterations - first_it
        if added:  # (costates and parameters of new rows are NaN: PlannerData.reserve)
            bounds = starts[: added + 1].tolist()
            data.trajectories.extend(traj[a:b] for a, b in pairwise(bounds))
            data.n_nodes = size + added
            its = node_it[:added].tolist()
            run.last_growth = its[-1]
            for it, d in zip(its, ends[:added].tolist(), strict=True):
                if d < run.best_goal:  # as the loop records a node nearer the goal
                    run.best_goal, run.since_nearer = d, 0
                    run.since_growth_nearer = run.iterations - it
        for index in tree.indices:
            index.commit(size + added)
        reasons = reasons.tolist()
        run.outcomes["added"] += reasons.count(0)
        run.outcomes["state_box"] += reasons.count(1)
        run.outcomes["nonfinite"] += reasons.count(2)
        run.edges_by["control"] += reasons.count(0)
        if code == 3:
            run.goal_node = size + added - 1
        elif code == 2:
            run.stalled = True
        return code == 1

    def _deferred_goal(self, tree: GrowingTree, size: int, added: int, traj: np.ndarray,
                       starts: np.ndarray, code: int):
        """The goal test of a compiled batch under the user's goal function: one call on
        every new state; the batch is cut at the first edge that reaches the goal region
        (that edge cut at its first state there, as `control_edge` cuts it). Returns the
        batch's code (3 when cut), how many of its nodes stay and their ends' distances."""
        prob, s = self.problem, self.settings
        n = prob.system.n_states
        first = np.zeros(len(traj), dtype=bool)
        first[starts[:-1]] = True  # each edge's first row is its parent's state
        rows = np.flatnonzero(~first)
        dist = prob.goal_distance(traj[rows])
        hits = np.flatnonzero(dist <= prob.goal_tolerance)
        last = starts[1 : added + 1] - 1  # each edge's last row
        ends = dist[np.searchsorted(rows, last)]
        if not hits.size:
            return code, added, ends
        row = int(rows[hits[0]])
        e = int(np.searchsorted(starts, row, side="right")) - 1  # the edge of that row
        steps = row - int(starts[e])
        node = size + e
        data = tree.data
        x = traj[row]
        u = data.controls[node]
        data.states[node] = x
        data.durations[node] = steps * s.dt
        data.costs[node] = steps * s.dt * self.propagator.hold_rate(u)
        for index in tree.indices:
            index.set(node, x[:n])
        tree.shifts[node] = prob.system.wrap_shift(x[None])[0]
        starts[e + 1] = row + 1
        ends = ends[: e + 1].copy()
        ends[e] = dist[hits[0]]
        return 3, e + 1, ends

    def batch_constants(self, tree: GrowingTree) -> _ExploreConsts | None:
        """`run_batch`'s constants for ``tree``'s node indices, or None where the iterations
        stay in Python (`compiled`)."""
        sys, s = self.problem.system, self.settings
        if not self.compiled:
            return None
        n, m = sys.n_states, sys.n_inputs
        boxes = np.zeros((8, max(n, m)))
        boxes[0, :n], boxes[1, :n] = sys.state_low, sys.state_high
        boxes[2, :n], boxes[3, :n] = self.propagator.box
        boxes[4, :m], boxes[5, :m] = self.draw_box()
        boxes[6, :n] = sys.state_low
        boxes[7, list(sys.angle_dims)] = 1.0
        goal, tol2 = np.zeros((3, n)), 0.0
        if self.propagator.ball is not None:
            goal[0], goal[1], goal[2], tol2 = self.propagator.ball
        consts = np.array([index.kernel_rows() for index in tree.indices], dtype=np.float64)
        floats = np.array([s.dt, s.goal_bias, tol2, s.time_weight])
        return _ExploreConsts(self.longest_hold(), floats, boxes, goal, consts)

    def draw_box(self, scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The box the inputs are drawn from at ``scale`` (default ``self.scale``): the
        control box shrunk by that factor towards its input nearest zero, where the running
        cost w + u^T R u / 2 is least (the whole box, as it is, at 1)."""
        low, high = self.propagator.control_box
        scale = self.scale if scale is None else scale
        if scale == 1.0:
            return low, high
        centre = np.clip(0.0, low, high)
        return centre + scale * (low - centre), centre + scale * (high - centre)

    def narrowest_scale(self) -> float:
        """The least scale worth drawing from (`draw_box`): the one at which the box's
        dearest corner costs as much as the time, u^T R u / 2 = w (R, w: the running cost's).
        Below it an input costs less than the time it is held, and a smaller box only makes
        paths longer. 1 where the whole box costs no more than that (nothing to narrow)."""
        r, w = self.propagator.input_weight, self.settings.time_weight

        def dearest(scale: float) -> float:
            low, high = self.draw_box(scale)
            corners = np.array(np.meshgrid(*zip(low, high, strict=True))).reshape(
                len(low), -1).T
            return float(0.5 * np.einsum("ki,ij,kj->k", corners, r, corners).max())

        if r is None or dearest(1.0) <= w:
            return 1.0
        lo, hi = 0.0, 1.0  # dearest(lo) < w < dearest(hi): bisection
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if dearest(mid) < w else (lo, mid)
        return hi

    def longest_hold(self) -> int:
        """The most RK4 steps a random-control edge holds its input: the data's longest
        segment."""
        return max(1, round(self.settings.max_duration / self.settings.dt))
