"""The learned steering (Alg. 1's expansion): the parent with the least predicted cost-to-go
J among the (node, target) queries that V accepts, steered by U's predicted costate; the
steering parameters drawn around U's prediction (truncated normals) and integrated as
extremals (`propagator.Propagator`). Knows nothing of random controls or the goal
connections; a `contracts.Steering`.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr, ndtri

from rrtcolearn.learn.models import LearnedFunctions, best_valid
from rrtcolearn.planning.contracts import Edge, GrowingTree
from rrtcolearn.planning.nearest import NodeIndex
from rrtcolearn.planning.propagator import Propagator
from rrtcolearn.planning.shooting import shoot

# a refined edge must end within this fraction of the goal tolerance of its aim (the
# shooting connection's tolerance, `connections.shoot_edge`)
LAND_FRACTION = 0.25
# refine only an edge that came at least this much nearer its aim than its start was:
# Newton's method converges from a guess in its basin, and an edge U did not steer toward
# the aim is not one (sparse_rrt's cart-pole: 523 refinements of such edges, none landed,
# 65% more CPU; docs/landing.md)
REFINE_PROGRESS = 0.5
# a solve stops refining after this many refinements in a row that did not land: where U's
# edges are not within Newton's reach of their aims the tries only cost CPU (the shipped
# acrobot's k-NN model: 2552 tries on 10 seeds, none landed, 25% more CPU; docs/landing.md)
REFINE_GIVE_UP = 50
# the derived ``edge_cost_ratio``: this quantile of the data's segments' costs over J's
# prediction for them from the other segments (`data_cost_ratio`), from at most
# COST_RATIO_ROWS of them (evenly spaced rows: deterministic)
COST_RATIO_QUANTILE = 0.99
COST_RATIO_ROWS = 3000


def data_cost_ratio(model: LearnedFunctions, quantile: float = COST_RATIO_QUANTILE,
                    rows: int = COST_RATIO_ROWS) -> float:
    """The ``quantile`` of cost / J over (at most ``rows`` of) the data's segments, J each
    segment's prediction without it: the k-NN J's mean cost of its m nearest other
    segments (leave one out), the networks' J their prediction. How far above J a true
    extremal's cost lies in the data; 1 without data."""
    t = model.training_
    X, cost = t["inputs"], t["cost"]
    if len(X) <= model.n_neighbors:
        return 1.0
    pick = np.unique(np.linspace(0, len(X) - 1, min(rows, len(X))).astype(np.int64))
    if model.networks_ is not None:
        J = model.query(X[pick])[0]
    else:
        m = model.n_neighbors
        Xs = model.features_.transform(X[pick]) * model.input_scale_
        # the segment itself is its own nearest point (its copies across an angle's seam
        # lie a turn away)
        _, idx = model.validity_.index_.query(Xs, m + 1)
        source = model.source_[idx]
        others = source != pick[:, None]
        # the first m neighbours that are other segments (stable: nearest first)
        order = np.argsort(~others, axis=1, kind="stable")[:, :m]
        near = np.take_along_axis(source, order, axis=1)
        J = cost[near].mean(axis=1)
        J = np.clip(J, *model.cost_bounds)
    return float(np.quantile(cost[pick] / J, quantile))


def _truncnorm(rng: np.random.Generator, mean: float, sigma: float, lo: float, hi: float) -> float:
    """One draw of N(mean, sigma) truncated to [lo, hi] by inverting the CDF."""
    a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
    if b - a < 1e-12:  # mean far outside the bounds: the nearest bound is the limit
        return lo if mean < lo else hi
    return float(np.clip(mean + sigma * ndtri(a + (b - a) * rng.random()), lo, hi))


def _truncnorm_inverse(u, mean, sigma: float, lo, hi, a, b):
    """N(mean, sigma) truncated to [lo, hi] at uniforms ``u``, where a and b are the CDF at the
    bounds (elementwise)."""
    return np.clip(mean + sigma * ndtri(a + (b - a) * u), lo, hi)


def _truncnorm_vec(rng: np.random.Generator, mean: np.ndarray, sigma: float, lo: np.ndarray,
                   hi: np.ndarray) -> np.ndarray:
    """`_truncnorm` elementwise; it draws a uniform for each coordinate that needs one, in
    order, so the draws and the generator's state are those of calling it coordinate by
    coordinate."""
    a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
    out = np.where(mean < lo, lo, hi)  # the nearest bound, where the mass is negligible
    draw = b - a >= 1e-12
    u = rng.random(int(draw.sum()))
    out[draw] = _truncnorm_inverse(u, mean[draw], sigma, lo[draw], hi[draw], a[draw], b[draw])
    return out


def goal_query(x0: np.ndarray, shift: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The learning queries (N, 2n) from states ``x0`` (N, n), or (1, 2n) from one (n,), to
    the goal: both ends shifted by whole turns (``shift``) into the box, the goal as
    ``x0 - offset`` (angles the short way)."""
    return np.atleast_2d(np.concatenate([x0 + shift, x0 - offset + shift], axis=-1))


class LearnedSteering:
    """Steering by the learned J, U and V (``model``).

    Settings it reads (`settings.PlannerSettings`, "learned steering"): ``sigma``,
    ``sigma_goal``, ``decimals``, ``control_samples``, ``max_candidates``,
    ``parent_cost_to_come``, ``edge_cost_ratio``,
    ``extend_distance``, ``max_resample``, ``data_reach`` (through ``reach``), and the
    duration's bounds ``dt`` and ``max_duration``.
    """

    kind = "learned"

    def __init__(self, propagator: Propagator, model: LearnedFunctions):
        self.propagator, self.model = propagator, model
        problem, s = propagator.problem, propagator.settings
        self.problem, self.settings = problem, s
        sys = problem.system
        # a query (x0, x1) farther apart than this cannot have m neighbours within V's
        # threshold, since every data pair is at most data_reach apart (weighted; a weighted
        # distance r is at most r / min(weight) raw)
        self.reach = float((s.data_reach + np.sqrt(2.0) * model.validity_.threshold
                            / model.n_neighbors) / float(np.min(s.metric_scale)))
        self._circular = np.zeros(sys.n_params, dtype=bool)
        self._circular[: len(sys.param_circular)] = sys.param_circular
        # the steering parameters' and the duration's bounds
        self._bounds = (np.append(sys.param_low, s.dt), np.append(sys.param_high, s.max_duration))
        n = sys.n_states
        self._lam, self._z0 = np.empty(n), np.empty(2 * n + 1)  # scratch: one extremal's start
        self._angles = list(sys.angle_dims)
        self.land_tolerance = LAND_FRACTION * problem.goal_tolerance
        self.guess = None  # U's last prediction (`propose`), for `guess_edge`
        self.cost_ratio = data_cost_ratio(model) if s.edge_cost_ratio == "data" \
            else float(s.edge_cost_ratio)
        self.reset()

    def reset(self) -> None:
        """Forget the landing record (`landing`): at the start of every solve."""
        self.errors: list[float] = []  # per edge returned: its end's distance to its aim
        self.refined = [0, 0, 0]  # refinements tried, landed and kept, failed in a row
        # draws found far dearer than J (`costly_edge`), and U's guess taken instead of all
        self.costly = [0, 0]

    def landing(self) -> dict:
        """The plan's ``landing`` record: learned edges made, the median distance of their
        ends to their aims (state units, angles the short way; 0 in the goal region), how
        many ended within ``land_tolerance`` of their aims, the refinements tried and
        kept."""
        return {"edges": len(self.errors),
                "median_error": float(np.median(self.errors)) if self.errors else None,
                "on_aim": int(np.sum(np.asarray(self.errors) <= self.land_tolerance)),
                "refined": self.refined[0], "landed": self.refined[1],
                "costly": self.costly[0], "guessed": self.costly[1],
                "cost_ratio": self.cost_ratio}

    def _offset(self, aim: np.ndarray, to_goal: bool):
        """States minus ``aim`` (angles the short way round), or the goal residual for a
        goal target (as the shooting connection aims)."""
        if to_goal:
            return self.problem.goal_residual
        angles = self._angles

        def offset(x: np.ndarray) -> np.ndarray:
            d = x - aim
            if angles:
                d[:, angles] = np.mod(d[:, angles] + np.pi, 2.0 * np.pi) - np.pi
            return d
        return offset

    def refine(self, x0: np.ndarray, edge: Edge, aim: np.ndarray, to_goal: bool
               ) -> Edge:
        """``edge`` (from ``x0``) made to land on ``aim``: Newton's method on its steering
        parameters and duration (`shooting.shoot`, the goal connection's solver), at most
        ``refine_iterations`` steps from the edge's own parameters, for an edge that ended
        within ``REFINE_PROGRESS`` of its start's distance to the aim, until ``REFINE_GIVE_UP``
        tries in a row failed in this solve. The refined edge is kept
        only if it ends within ``land_tolerance`` of the aim (or in the goal region) and
        passes every check of an edge, uncut; else ``edge`` as it was."""
        sys, s = self.problem.system, self.settings
        n = sys.n_states
        offset = self._offset(aim, to_goal)
        if self.refined[2] >= REFINE_GIVE_UP:
            return edge
        miss = float(np.linalg.norm(offset(edge.traj[-1:, :n].copy())))
        if edge.hit or miss <= self.land_tolerance or \
                miss > REFINE_PROGRESS * float(np.linalg.norm(offset(x0[None].copy()))):
            return edge
        self.refined[0] += 1
        res = shoot(sys, x0, edge.params[:-1], edge.params[-1], offset,
                    time_weight=s.time_weight, dt=s.dt, max_duration=s.max_duration,
                    tolerance=self.land_tolerance, max_iterations=s.refine_iterations)
        self.refined[2] += 1
        if res is None:
            return edge
        params = np.append(res.params, res.steps * s.dt)
        lam, z0 = self._lam, self._z0
        rejected = self.propagator.rejected
        new = self.propagator.extremal_edges(x0, params[None], lam[None]) \
            if self.propagator.start_extremal(x0, params, lam, z0) else None
        self.propagator.rejected = rejected
        # the duration is rounded to the RK4 grid: the landing is checked on the edge made
        if new is None or not (new.hit or (
                new.steps == res.steps and np.linalg.norm(
                    offset(new.traj[-1:, :n].copy())) <= self.land_tolerance)):
            return edge
        self.refined[1] += 1
        self.refined[2] = 0
        return new

    @property
    def rejected(self) -> str:
        """Why the last `steer` gave no edge (`contracts.OUTCOMES`)."""
        return self.propagator.rejected

    def _sample_params(self, rng, prediction: np.ndarray, sigma: float) -> np.ndarray:
        sys, s = self.problem.system, self.settings
        k = sys.n_params
        if not self._circular.any():
            # every coordinate a truncated normal: one vector of uniforms, the same numbers
            # (and so the same draws) as the coordinate-by-coordinate loop below
            return np.round(_truncnorm_vec(rng, prediction[: k + 1], sigma, *self._bounds),
                            s.decimals)
        out = np.empty(k + 1)
        for j in range(k):
            lo, hi = sys.param_low[j], sys.param_high[j]
            if self._circular[j]:
                v = prediction[j] + sigma * rng.standard_normal()
                v = np.round(v, s.decimals)
                out[j] = lo + np.mod(v - lo, hi - lo)
            else:
                out[j] = np.round(_truncnorm(rng, prediction[j], sigma, lo, hi), s.decimals)
        out[k] = np.round(_truncnorm(rng, prediction[k], sigma, s.dt, s.max_duration), s.decimals)
        return out

    def nearest(self, states: np.ndarray, target: np.ndarray, weight: np.ndarray,
                 wrapped: NodeIndex) -> tuple[int, np.ndarray, float]:
        """The tree node nearest ``target`` (weighted, angles modulo a turn): its index, the
        offset to the target (angles the short way round) and the weighted distance."""
        i = int(wrapped.nearest(target, 1)[0])
        diff = target - states[i]
        angles = list(self.problem.system.angle_dims)
        if angles:
            diff[angles] = np.mod(diff[angles] + np.pi, 2.0 * np.pi) - np.pi
        wd = diff * weight
        return i, diff, float(np.sqrt(wd @ wd))

    def _extend(self, states: np.ndarray, target: np.ndarray, weight: np.ndarray,
                wrapped: NodeIndex) -> np.ndarray:
        """``target`` moved to within ``extend_distance`` of its nearest node (weighted, angles
        modulo a turn)."""
        i, diff, dist = self.nearest(states, target, weight, wrapped)
        factor = min(1.0, self.settings.extend_distance / dist) if dist > 0 else 1.0
        return states[i] + factor * diff

    def _edge(self, rng, x0: np.ndarray, prediction: np.ndarray, sigma: float,
              lam: np.ndarray, z0: np.ndarray):
        """One edge from ``x0``: steering parameters drawn around ``prediction``, integrated,
        checked and cut; None when the draw gives no edge."""
        # redraw parameters whose costate does not exist or whose input already breaks
        # the limit at the start: such an edge would be rejected without integrating it
        self.propagator.rejected = "no_costate"
        for _ in range(self.settings.max_resample):
            params = self._sample_params(rng, prediction, sigma)
            if self.propagator.start_extremal(x0, params, lam, z0):
                return self.propagator.extremal_edges(x0, params[None], lam[None])
        return None

    def _draws(self, rng, x0: np.ndarray, prediction: np.ndarray, sigma: float, count: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``count`` steering draws around ``prediction`` that have a costate, drawn in
        blocks (parameters and costates vectorised): (parameters (c, k+1), costates (c, n))."""
        sys, s = self.problem.system, self.settings
        lo, hi = self._bounds
        mean = np.broadcast_to(prediction[: lo.size], (2 * count, lo.size))
        a, b = ndtr((lo - mean) / sigma), ndtr((hi - mean) / sigma)
        kept_p, kept_l, have = [], [], 0
        for _ in range(s.max_resample):
            u = rng.random(mean.shape)
            p = np.where(b - a < 1e-12, np.where(mean < lo, lo, hi),
                         _truncnorm_inverse(u, mean, sigma, lo, hi, a, b))
            p = np.round(p, s.decimals)
            with np.errstate(invalid="ignore"):  # rows without a costate are NaN
                lam, valid = sys.costate_from_params(
                    np.broadcast_to(x0, (len(p), x0.size)), p[:, :-1], s.time_weight)
            kept_p.append(p[valid])
            kept_l.append(lam[valid])
            have += int(valid.sum())
            if have >= count:
                break
        self.propagator.rejected = "no_costate"
        return np.concatenate(kept_p)[:count], np.concatenate(kept_l)[:count]

    def steer(self, rng: np.random.Generator, tree: GrowingTree, target: np.ndarray,
              to_goal: bool) -> tuple[int, Edge | None]:
        """`propose`'s edge, refined to land on its aim (`refine`) when
        ``refine_iterations`` > 0; its landing error recorded."""
        parent, edge, aim = self.propose(rng, tree, target, to_goal)
        if edge is None:
            return parent, edge
        x0 = tree.states[parent]
        if self.settings.refine_iterations:
            edge = self.refine(x0, edge, aim, to_goal)
        n = self.problem.system.n_states
        end = edge.traj[-1:, :n].copy()
        self.errors.append(0.0 if edge.hit else
                           float(np.linalg.norm(self._offset(aim, False)(end))))
        return parent, edge

    def guess_edge(self, x0: np.ndarray, aim: np.ndarray, weight: np.ndarray) -> Edge | None:
        """The edge of U's last prediction (`propose`'s ``guess``) itself from ``x0``: its
        parameters rounded and kept in their bounds (circular ones wrapped), cut at its
        state nearest ``aim`` like the drawn edges (with more than one draw); None when it
        gives no edge."""
        s = self.settings
        lo, hi = self._bounds
        k = lo.size - 1
        params = np.round(self.guess[: k + 1], s.decimals)
        circ = np.append(self._circular, False)
        params = np.where(circ, lo + np.mod(params - lo, hi - lo), np.clip(params, lo, hi))
        lam, z0 = self._lam, self._z0
        if not self.propagator.start_extremal(x0, params, lam, z0):
            return None
        if s.control_samples > 1:
            return self.propagator.extremal_edges(x0, params[None], lam[None], aim, weight)
        return self.propagator.extremal_edges(x0, params[None], lam[None])

    def costly_edge(self, x0: np.ndarray, shift: np.ndarray, edge: Edge, aim: np.ndarray
                    ) -> bool:
        """Whether ``edge`` from ``x0`` (``shift``: the parent's whole turns into the data's
        box) costs more than ``cost_ratio`` times the learned J between its ends, or than
        that multiple of J from ``x0`` to its ``aim``: a draw around U's guess that went
        through large inputs where the data knows a cheaper extremal between the same
        ends, or that paid more than the whole way to its aim should cost."""
        n = x0.size
        query = np.stack([np.concatenate([x0, edge.traj[-1, :n]]),
                          np.concatenate([x0, aim])]) + np.tile(shift, 2)
        return edge.cost > self.cost_ratio * float(self.model.query(query)[0].min())

    def propose(self, rng: np.random.Generator, tree: GrowingTree, target: np.ndarray,
                to_goal: bool) -> tuple[int, Edge | None, np.ndarray]:
        """Alg. 1's expansion: the parent with the least predicted J among the valid queries
        (with ``parent_cost_to_come``: the least cost-to-come plus J), steered by U.
        (parent, edge); the edge is None (and ``rejected`` says why) when no node is within
        reach, V rejects every query or no draw gives an edge.

        With ``edge_cost_ratio`` (`cost_ratio`) a draw dearer than that multiple of J
        (`costly_edge`) is passed over for the next nearest, then for U's guess itself;
        with none left the query counts as rejected (``invalid_query``)."""
        prob, sys, s = self.problem, self.problem.system, self.settings
        states, weight, wrapped = tree.states, tree.weight, tree.wrapped
        lam, z0, reach2 = self._lam, self._z0, self.reach * self.reach
        n, m = sys.n_states, len(states)
        none = (-1, None, target)
        if s.extend_distance and not to_goal:
            target = self._extend(states, target, weight, wrapped)
        aim_images = to_goal and prob.wrap_goal
        if s.max_candidates is not None:
            # the nearest (weighted) nodes only, from the index: the iteration's cost does
            # not grow with the tree
            near = (wrapped if aim_images else tree.plain).nearest(target, s.max_candidates)
        else:  # the paper's planner: every node within reach
            near = np.arange(m)
        # each node aims at the goal's image nearest to it (angles modulo a turn)
        aims = states[near] - prob.offset_to(states[near], target) if aim_images \
            else target
        diff = states[near] - aims
        within = np.einsum("ij,ij->i", diff, diff) <= reach2
        near = near[within]
        if near.size == 0:
            self.propagator.rejected = "out_of_reach"
            return none
        order = np.argsort(near)  # candidates in node order, as the paper's planner has them
        near = near[order]
        if aim_images:
            aims = aims[within][order]
        sh = tree.shifts[near]
        query = np.concatenate([states[near] + sh, aims + sh], axis=1)
        row, neighbours = best_valid(self.model, query, tree.data.cost_to_come(near)
                                     if s.parent_cost_to_come else None)
        if row < 0:
            self.propagator.rejected = "invalid_query"
            return none
        parent = int(near[row])
        prediction = self.model.steer(query[row : row + 1],
                                      None if neighbours is None else neighbours[None])[0]
        self.guess = prediction
        x0 = states[parent]
        aim = aims[row] if aim_images else target
        sigma = s.sigma_goal if to_goal else s.sigma
        shift = tree.shifts[parent]
        if s.control_samples > 1 and not self._circular.any():
            params, costates = self._draws(rng, x0, prediction, sigma, s.control_samples)
            edge = self.propagator.extremal_edges(x0, params, costates, aim, weight)
            dropped = False
            while self.cost_ratio and edge is not None and \
                    self.costly_edge(x0, shift, edge, aim):
                # the next nearest draw instead
                self.costly[0] += 1
                dropped = True
                other = (costates != edge.costate).any(axis=1)
                params, costates = params[other], costates[other]
                edge = self.propagator.extremal_edges(x0, params, costates, aim, weight) \
                    if other.any() else None
            return parent, self._guess_instead(x0, shift, aim, weight) if dropped and \
                edge is None else edge, aim
        # one draw at a time (the paper's planner)
        cands = (self._edge(rng, x0, prediction, sigma, lam, z0)
                 for _ in range(s.control_samples))
        edge, best_d2 = None, np.inf
        for cand in cands:
            if cand is None:
                continue
            if s.control_samples == 1 or cand.hit:  # the paper's single draw, or a goal hit
                edge = cand
                break
            # OMPL's directed control sampling: keep the draw ending nearest the target,
            # cut at its state nearest the target
            wd = (cand.traj[1:, :n] - aim) * weight
            d2 = np.einsum("ij,ij->i", wd, wd)
            k = int(np.argmin(d2))
            if d2[k] < best_d2:
                best_d2 = float(d2[k])
                traj_c, params_c = cand.traj[: k + 2], cand.params.copy()
                params_c[-1] = (k + 1) * s.dt
                u_c = float(np.abs(sys.optimal_control(
                    traj_c[:, :n], traj_c[:, n : 2 * n])).max())
                edge = Edge(traj_c, k + 1, float(traj_c[-1, 2 * n]), u_c, False, params_c,
                            cand.costate)
        if self.cost_ratio and edge is not None and self.costly_edge(x0, shift, edge, aim):
            self.costly[0] += 1
            edge = self._guess_instead(x0, shift, aim, weight)
        return parent, edge, aim

    def _guess_instead(self, x0: np.ndarray, shift: np.ndarray, aim: np.ndarray,
                       weight: np.ndarray) -> Edge | None:
        """When every draw was far dearer than J (`costly_edge`): U's guess itself if it
        is not, else None, the learned functions rejecting the query (as V does)."""
        edge = self.guess_edge(x0, aim, weight)
        if edge is None or self.costly_edge(x0, shift, edge, aim):
            self.propagator.rejected = "invalid_query"
            return None
        self.costly[1] += 1
        return edge
