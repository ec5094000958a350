"""The goal funnel: extremals integrated backwards in time from the goal.

Every state x on such an extremal reaches the goal exactly along it, with the costate found
there; the states of a few thousand of them fill a four-dimensional neighbourhood of the
paths that end at the goal (three costate directions on H* = 0 and the time to go). Where
the boundary value problem into the goal is ill-conditioned, as into the acrobot's upright,
Newton's method started from U's guess does not converge (docs/method.md), but started from a
funnel extremal that passes near a tree node it often does: the funnel's solution is moved
to the node in small steps (continuation), each solved backwards from the goal, where the unknowns
are the goal's costate and the duration; a last forward solve from the node itself
(`shooting.shoot`) gives the edge the planner checks like any other.

The planner's funnel is one query's (`FunnelStream`): its extremals are drawn from a stream
of the query's seed, and each part is built once and shared by the query's solves (anytime
planning's restarts), so that only the first solve that needs a part pays for it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from rrtcolearn.integrate import rollout_batch
from rrtcolearn.planning.shooting import endpoints, newton
from rrtcolearn.systems.base import System

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

_CHUNK = 2000  # backward simulations per batched RK4 call (bounds the memory)
# continuation from the funnel state to the node: first, smallest and largest steps (as
# fractions of the way); a step halves after a failed solve and, until the first failure,
# doubles after a good one, so at most 5 solves fail per continuation
_FIRST_STEP, _MIN_STEP, _MAX_STEP = 0.1, 1.0 / 64, 0.25
_STAGE_TOLERANCE = 1e-4  # state residual of the intermediate continuation steps
_FINAL_TOLERANCE = 1e-9  # ... and of the last: the forward solve starts from its costate


class Continuation(NamedTuple):
    """`GoalFunnel.steer`'s extremal from a state to the goal: its costate at the state,
    its duration (s) and its costate at the goal (it integrates backwards from there)."""

    costate: np.ndarray
    duration: float
    goal_costate: np.ndarray


@dataclass(frozen=True)
class GoalFunnel:
    """States (M, n) on backward extremals from ``goal``, each with the index of its
    simulation (M,) and its time to go in RK4 steps (M,); ``goal_costates`` (S, n) are the
    simulations' costates at the goal. ``offset`` is the goal test's state-minus-goal; the
    states' offsets are not kept (the index holds them scaled): of millions of states
    (the acrobot's 2.8 million) they were a third of the funnel's memory. The index is
    built when first asked for (`index`): the aimed search's funnels (`AimedSearch`) are
    never searched by it."""

    system: System
    goal: np.ndarray
    states: np.ndarray
    simulation: np.ndarray
    steps: np.ndarray
    cost_to_go: np.ndarray  # (M,) float32: the extremal's cost from the state to the goal
    goal_costates: np.ndarray
    offset: Callable[[np.ndarray], np.ndarray]
    scale: np.ndarray
    time_weight: float
    dt: float

    @cached_property
    def index(self) -> cKDTree:
        """The kd-tree of the states' goal offsets times ``scale``, built on first use."""
        from scipy.spatial import cKDTree  # (here: a plan's start-up does not import it)

        # split at the midpoint of the widest side, without the median's partial sorts, no
        # shrinking of the nodes' boxes, leaves of up to 32 points (scipy's default 16):
        # a faster build of the same points (0.5-0.7 s instead of 1.0-1.4 s for the 1.7-2.8
        # million states of the acrobot's, cart-pole's and pendulum's funnels), queries no
        # slower, the same neighbours and distances (an exact search either way)
        return cKDTree(self.offsets * self.scale, leafsize=32, balanced_tree=False,
                       compact_nodes=False)

    @property
    def offsets(self) -> np.ndarray:
        """The states' goal offsets (M, n), computed again (`offset` row by row: the same
        values as at the build)."""
        return self.offset(self.states) if len(self.states) else self.states

    @classmethod
    def build(cls, system: System, goal: np.ndarray, offset: Callable[[np.ndarray], np.ndarray],
              rng: np.random.Generator | FunnelDraws, *, n_simulations: int,
              time_weight: float, dt: float, max_duration: float, max_cost: float,
              scale: np.ndarray, tolerance: float, min_duration: float = 0.0,
              box: tuple[np.ndarray, np.ndarray] | None = None) -> GoalFunnel:
        """``n_simulations`` extremals from ``goal`` with costates drawn as the data's
        (uniform steering parameters, H* = 0), integrated backwards for at most
        ``max_duration`` or until their |cost| exceeds ``max_cost``. Only states inside the
        state box (non-angle coordinates) all the way to the goal are kept: tree nodes and edges
        lie there, and only those outside the goal region (radius ``tolerance``): a node
        there has arrived. ``offset`` is the goal test's state-minus-goal (angles wrapped
        when it wraps them). States closer than ``min_duration`` to the goal are dropped:
        where little time is left, the boundary value problem from near them can be too
        ill-conditioned to solve (the acrobot's, docs/method.md). ``box`` is the state constraints
        (low, high), the sampling box by default. ``rng``: the generator the steering
        parameters are drawn from, or a query's shared stream (`FunnelDraws`: the next
        ``n_simulations`` extremals of `FunnelStream`, built once per query)."""

        def of(params: np.ndarray) -> GoalFunnel:
            return cls._of_params(system, goal, offset, params, time_weight=time_weight, dt=dt,
                                  max_duration=max_duration, max_cost=max_cost, scale=scale,
                                  tolerance=tolerance, min_duration=min_duration, box=box)

        if isinstance(rng, FunnelDraws):
            return rng.next(n_simulations, system, of)
        return of(rng.uniform(system.param_low, system.param_high,
                              (n_simulations, system.n_params)))

    @classmethod
    def _of_params(cls, system: System, goal: np.ndarray,
                   offset: Callable[[np.ndarray], np.ndarray], params: np.ndarray, *,
                   time_weight: float, dt: float, max_duration: float, max_cost: float,
                   scale: np.ndarray, tolerance: float, min_duration: float,
                   box: tuple[np.ndarray, np.ndarray] | None) -> GoalFunnel:
        """`build`'s funnel of the extremals with steering parameters ``params`` (S, p)."""
        n = system.n_states
        goal = np.asarray(goal, dtype=np.float64)
        n_simulations = len(params)
        lam, valid = system.costate_from_params(np.repeat(goal[None], n_simulations, axis=0),
                                                params, time_weight)
        lam = lam[valid]
        max_steps = max(1, int(max_duration / dt))
        bounded = system.bounded_dims
        low, high = (system.state_low, system.state_high) if box is None else box
        lo, hi = low[bounded], high[bounded]
        # stop each extremal once it is certainly outside the box: beyond the ball around the
        # goal, in the bounded coordinates scaled by the box's widths, that holds the box
        ball = np.zeros(n)
        ball[bounded] = 1.0 / (hi - lo)
        radius = float(np.sqrt(np.sum((np.maximum(hi - goal[bounded], goal[bounded] - lo)
                                       * ball[bounded]) ** 2)))
        kept_states, kept_sims, kept_steps, kept_costs = [], [], [], []
        for first in range(0, len(lam), _CHUNK):
            chunk = lam[first : first + _CHUNK]
            z0 = np.zeros((len(chunk), 2 * n + 1))
            z0[:, :n] = goal
            z0[:, n : 2 * n] = chunk
            states, costs, lengths, _ = rollout_batch(system, z0, time_weight, -dt,
                                                      max_steps, max_cost, radius, n,
                                                      scale=ball)
            # each extremal's valid steps only (its first lengths[i]; most stop far short of
            # max_steps), extremal by extremal: the arrays beyond them are never read
            lengths = np.asarray(lengths, dtype=np.int64)
            sims = np.repeat(np.arange(len(chunk)), lengths)
            steps = np.arange(len(sims)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
            points = states[sims, steps]
            inside = ((points[:, bounded] >= lo) & (points[:, bounded] <= hi)).all(axis=1)
            # a state counts only if the whole way from it to the goal stays in the box: the
            # steps of an extremal before its first state outside it
            first_out = np.full(len(chunk), max_steps)
            out, at = np.unique(sims[~inside], return_index=True)
            first_out[out] = steps[~inside][at]
            keep = (steps < first_out[sims]) & ((steps + 1) * dt >= min_duration)
            sims, steps = sims[keep], steps[keep]
            kept_states.append(points[keep])
            kept_sims.append(sims + first)
            kept_steps.append(steps + 1)
            kept_costs.append(np.abs(costs[sims, steps]).astype(np.float32))
        states = np.concatenate(kept_states) if kept_states else np.empty((0, n))
        sims = np.concatenate(kept_sims) if kept_sims else np.empty(0, np.int64)
        steps = np.concatenate(kept_steps) if kept_steps else np.empty(0, np.int64)
        to_go = np.concatenate(kept_costs) if kept_costs else np.empty(0, np.float32)
        del kept_states, kept_sims, kept_steps, kept_costs  # (each held once from here on)
        offsets = offset(states) if len(states) else states
        outside = np.einsum("ij,ij->i", offsets, offsets) > tolerance**2
        del offsets
        states, sims, steps, to_go = states[outside], sims[outside], steps[outside], \
            to_go[outside]
        return cls(system, goal, states, sims.astype(np.int32), steps.astype(np.int32), to_go,
                   lam, offset, np.asarray(scale, dtype=np.float64), float(time_weight),
                   float(dt))

    def __len__(self) -> int:
        return len(self.states)

    def extremal(self, j: int) -> Continuation:
        """Funnel state ``j``'s own extremal as a `Continuation` from it: its costate there
        (integrated backwards from the goal again), its time to go and its goal costate."""
        n = self.system.n_states
        lam = self.goal_costates[self.simulation[j]]
        duration = float(self.steps[j]) * self.dt
        z, _ = endpoints(self.system, self.goal, np.append(lam, duration)[None],
                         self.time_weight, -self.dt)
        return Continuation(z[0, n : 2 * n].copy(), duration, lam.copy())

    def nearest(self, offsets: np.ndarray, k: int, radius: float
                ) -> tuple[np.ndarray, np.ndarray]:
        """Weighted distances (N, k) from states given by their goal offsets (N, n) to
        their k nearest funnel states within ``radius`` (inf where there are fewer), and
        those states' indices (N, k)."""
        # the bound also keeps the search short: most nodes have no funnel state near them
        d, i = self.index.query(np.atleast_2d(offsets) * self.scale, k=k,
                                distance_upper_bound=radius)
        return d.reshape(-1, k), np.minimum(i.reshape(-1, k), len(self.states) - 1)

    def steer(self, offset: np.ndarray, j: int, max_duration: float) -> Continuation | None:
        """Costate and duration of an extremal from the state with goal offset ``offset``
        (n,) to the goal, found by continuation from funnel state ``j`` (and its costate at
        the goal, from which the extremal integrates backwards to the state); None when a
        step of the continuation does not converge. The result is a first guess for a
        forward solve: its end is exact only up to the RK4 grid.

        Each step's Newton solve starts from the secant predictor (the last two solutions
        extrapolated to the new target), and once a step has failed the step no longer
        grows: near a fold of the branch the old rule (double after every success) went on
        doubling and halving for up to 25 solves before giving up. Both measured side by
        side on bench/ablation.py's models (docs/ablation.md, "Continuation along the
        funnel"): the same first paths on the pendulums and acrobot, cheaper ones on the
        cart-pole, at 0.92x the acrobot's CPU per seed."""
        xb = self.states[j]
        # the node, shifted to the funnel state's turn
        x = xb + (offset - self.offset(self.states[j : j + 1])[0])
        # the solution (costate, duration) at fraction ``done`` of the way, and the one
        # before it (``last`` at ``last_done``): the secant predictor's two points
        v = np.append(self.goal_costates[self.simulation[j]], int(self.steps[j]) * self.dt)
        last, last_done = v, 0.0
        done, step, sol, failed = 0.0, _FIRST_STEP, None, False
        while done < 1.0:
            nxt = min(1.0, done + step)
            target = xb + nxt * (x - xb)
            guess = v if done == 0.0 else v + (nxt - done) / (done - last_done) * (v - last)
            sol = newton(self.system, self.goal, guess[:-1], float(guess[-1]),
                         lambda y, t=target: np.atleast_2d(y) - t,
                         time_weight=self.time_weight, dt=-self.dt, max_duration=max_duration,
                         tolerance=_FINAL_TOLERANCE if nxt == 1.0 else _STAGE_TOLERANCE)
            if sol is None:
                failed, step = True, 0.5 * step
                if step < _MIN_STEP:
                    return None
                continue
            last, last_done, v, done = v, done, sol[0], nxt
            if not failed:
                step = min(2.0 * step, _MAX_STEP)
        n = self.system.n_states
        return Continuation(sol[1][n : 2 * n].copy(), float(v[-1]), v[:-1].copy())


# the spawn key, under the query's seed, of the funnel's random stream ("funn"): apart from
# every stream anytime planning's solves draw from (their seeds are integers generated from
# children (0,), (1,), ... of the query's seed sequence)
FUNNEL_STREAM = 0x66756E6E
AIM_STREAM = 0x61696D  # ... and, under it, the aimed search's ("aim")

# `AimedSearch`: the extremals kept (nearest the target first), new draws around each per
# round, their spread in the first round (a fraction of each steering parameter's range)
# and its factor per round, and the rounds in all (docs/anytime.md, "Funnel extremals
# through the start")
AIM_POOL, AIM_DRAWS, AIM_SIGMA, AIM_SHRINK, AIM_ROUNDS = 5, 64, 0.05, 0.6, 12
# the pool's nearest extremal is steered along again only once it is this much nearer than
# the last one tried (each try, a continuation and multiple shooting, costs 0.1-1.5 s)
AIM_RETRY = 0.7


class AimedSearch:
    """Extremals from the goal that pass through one state (a query's start), found by a
    random local search over their steering parameters at the goal.

    Where the boundary value problem from the start to the goal is too ill-conditioned for
    Newton's method (the acrobot's 5-s swing-up: single, backward and multiple shooting from
    the funnel extremals passing 0.85 from the start all fail), the funnel's extremals
    still pass near the start, and the distance of an extremal to the start is a
    continuous function of its goal costate: the search keeps the ``AIM_POOL`` extremals
    passing nearest it (each at its nearest state), draws ``AIM_DRAWS`` new ones around
    each (normal, ``AIM_SIGMA`` of each parameter's range, shrinking by ``AIM_SHRINK`` per
    round) and keeps the nearest again. Each round's pool is a funnel (`GoalFunnel`) the
    funnel connection can steer along from the start."""

    def __init__(self, target: np.ndarray, system: System,
                 offset_to: Callable[[np.ndarray, np.ndarray], np.ndarray],
                 rng: np.random.Generator, parts: list[GoalFunnel]):
        self.target = np.array(target, dtype=np.float64)
        self.system, self.offset_to, self.rng = system, offset_to, rng
        self.rounds = 0
        # the pool: (distance, steering parameters at the goal, cost to go from the nearest
        # state) of each kept extremal, nearest first
        self.pool: list[tuple[float, np.ndarray, float]] = []
        for part in parts:
            self._keep(part)

    @property
    def nearest(self) -> float:
        """The weighted distance of the pool's nearest extremal to the target."""
        return self.pool[0][0] if self.pool else float("inf")

    @property
    def cheapest(self) -> float:
        """The least cost to go of the pool's extremals from their states nearest the
        target: about what a path from the target along one of them would cost."""
        return min((c for _, _, c in self.pool), default=float("inf"))

    def distances(self, funnel: GoalFunnel) -> np.ndarray:
        """The weighted distance of each of ``funnel``'s states to the target (M,)."""
        d = self.offset_to(funnel.states, self.target) * funnel.scale
        return np.sqrt(np.einsum("ij,ij->i", d, d))

    def _keep(self, funnel: GoalFunnel) -> None:
        """The pool updated with ``funnel``'s extremals (each at its state nearest the
        target)."""
        if not len(funnel):
            return
        dist = self.distances(funnel)
        order = np.argsort(dist, kind="stable")
        _, first = np.unique(funnel.simulation[order], return_index=True)
        best = order[first[np.argsort(dist[order[first]], kind="stable")]][:AIM_POOL]
        lam = funnel.goal_costates[funnel.simulation[best]]
        params = self.system.params_from_costate(np.broadcast_to(funnel.goal, lam.shape), lam)
        self.pool = sorted(self.pool + list(zip(dist[best].tolist(), params,
                                                funnel.cost_to_go[best].tolist(),
                                                strict=True)), key=lambda e: e[0])[:AIM_POOL]

    def step(self, build: Callable[[np.ndarray], GoalFunnel]) -> GoalFunnel | None:
        """One round (None once ``AIM_ROUNDS`` are done or the pool is empty): draws around
        the pool's extremals, the nearest kept; the funnel of the pool's extremals."""
        if self.rounds >= AIM_ROUNDS or not self.pool:
            return None
        sys = self.system
        lo, hi = sys.param_low, sys.param_high
        sigma = AIM_SIGMA * AIM_SHRINK ** self.rounds * (hi - lo)
        self.rounds += 1
        centres = np.array([p for _, p, _ in self.pool])
        draws = centres[:, None, :] + sigma * self.rng.standard_normal(
            (len(centres), AIM_DRAWS, len(lo)))
        self._keep(build(np.clip(draws.reshape(-1, len(lo)), lo, hi)))
        return build(np.array([p for _, p, _ in self.pool]))



class FunnelStream:
    """The goal funnel of one query, shared by its solves.

    The steering parameters of the funnel's extremals come from a random stream of their own
    that depends on the query's seed only (`of_query`), not on a solve's generator: the k-th
    extremal is the same in every solve of the query. The funnel is built in parts (the
    automatic funnel's first part and each doubling, `connections.FunnelConnection`); each
    part, the extremals [first, first + k) of the stream, is built once, when a solve first
    needs it, and kept: a query's later solves take the parts built so far as they are
    (their kd-trees too) and build only those beyond. A solve uses the parts its own growth
    asks for, in its own turn (`draws`), so what it does is the same whichever solves ran
    before it: the plans stay a function of their seeds. A stream serves one planner (the
    parts are its funnel's, of its settings).

    The search for extremals through the start (`aimed`) is the one stateful part: it
    belongs to one run of the query (an anytime run: its first solve calls `begin`), is
    seeded with the parts that run used, and draws from a generator restarted with the run,
    so a second run of the query is the first again, not its continuation."""

    def __init__(self, rng: np.random.Generator, aim_rng: np.random.Generator | None = None):
        self._rng = rng
        self._params: np.ndarray | None = None  # (drawn, p): the stream's parameters so far
        self.parts: dict[tuple[int, int], GoalFunnel] = {}  # (first, k) -> the part
        self.built = 0  # parts built (each once)
        # the funnel's builder from steering parameters (the last part's), and the search
        # for extremals through the query's start (`aimed`), with a generator of its own
        self.build: Callable[[np.ndarray], GoalFunnel] | None = None
        self._aim_seed = aim_rng.bit_generator.seed_seq if aim_rng is not None else None
        self._aim_rng = aim_rng
        self._aimed: AimedSearch | None = None
        self.used: list[tuple[int, int]] = []  # the parts this run used, in turn

    def begin(self) -> None:
        """A new run of the query: the parts kept, the search through the start
        (`aimed`) and its generator restarted, the parts used so far forgotten."""
        self._aimed, self.used = None, []
        if self._aim_seed is not None:
            self._aim_rng = np.random.default_rng(self._aim_seed)

    @classmethod
    def of_query(cls, query: int | np.random.SeedSequence) -> FunnelStream:
        """The funnel's stream of the query with seed ``query``: spawned under it
        (`FUNNEL_STREAM`)."""
        if isinstance(query, np.random.SeedSequence):
            seq = np.random.SeedSequence(query.entropy,
                                         spawn_key=(*query.spawn_key, FUNNEL_STREAM))
        else:
            seq = np.random.SeedSequence(int(query), spawn_key=(FUNNEL_STREAM,))
        aim = np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, AIM_STREAM))
        return cls(np.random.default_rng(seq), np.random.default_rng(aim))

    def draws(self) -> FunnelDraws:
        """One funnel's parts in turn, from the stream's first extremal (`GoalFunnel.build`
        with this as its ``rng``)."""
        return FunnelDraws(self)

    def part(self, first: int, k: int, system: System,
             build: Callable[[np.ndarray], GoalFunnel]) -> GoalFunnel:
        """The funnel of the stream's extremals [first, first + k): ``build(params)`` the
        first time, then the same part. The stream's parameters are drawn in order (a
        generator's uniform draws split into several calls are the same numbers as in one)."""
        key = (first, k)
        self.build = build
        if key not in self.parts:
            p = system.n_params
            have = 0 if self._params is None else len(self._params)
            if have < first + k:
                more = self._rng.uniform(system.param_low, system.param_high,
                                         (first + k - have, p))
                self._params = more if self._params is None else \
                    np.concatenate([self._params, more])
            self.parts[key] = build(self._params[first : first + k])
            self.built += 1
        if key not in self.used:
            self.used.append(key)
        return self.parts[key]

    def aimed(self, start: np.ndarray, system: System,
              offset_to: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> AimedSearch | None:
        """The search for extremals through ``start`` (`AimedSearch`), seeded with the
        extremals of the parts this run used so far that pass nearest it; kept for the
        run's later calls. None before any part is used, or for another start."""
        if self.build is None or not self.used:
            return None
        if self._aimed is None:
            if self._aim_rng is None:  # (a stream not made by `of_query`)
                self._aim_seed = self._rng.bit_generator.seed_seq.spawn(1)[0]
                self._aim_rng = np.random.default_rng(self._aim_seed)
            self._aimed = AimedSearch(start, system, offset_to, self._aim_rng,
                                      [self.parts[key] for key in self.used])
        return self._aimed if np.array_equal(self._aimed.target, start) else None

    def __len__(self) -> int:
        """Extremals drawn so far."""
        return 0 if self._params is None else len(self._params)


class FunnelDraws:
    """One funnel's way through a `FunnelStream`: each call of `GoalFunnel.build` with it
    gives the next ``n_simulations`` extremals of the stream (built once per stream)."""

    def __init__(self, stream: FunnelStream):
        self.stream = stream
        self.drawn = 0

    def next(self, k: int, system: System, build: Callable[[np.ndarray], GoalFunnel]
             ) -> GoalFunnel:
        part = self.stream.part(self.drawn, k, system, build)
        self.drawn += k
        return part
