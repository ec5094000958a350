"""The planner's tree (OMPL's PlannerData) and the plan it yields."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# columns whose unwritten rows are NaN: a control edge has no costate or parameters, an
# extremal no control
_NAN_FILLED = ("controls", "costates", "params")


class PlannerData:
    """A growing tree: node states, parent links, and the edge that reached each node.

    Edge i (into node i) starts at ``states[parents[i]]`` with ``costates[i]`` and runs for
    ``durations[i]`` seconds at cost ``costs[i]``; ``params[i]`` are the steering parameters
    that produced it, ``max_abs_u[i]`` the largest |u| along it. A control edge (a constant
    input, the planner's random-control expansion) has ``controls[i]`` and NaN costate and
    parameters; an extremal edge has NaN controls. ``trajectories[i]`` holds
    its integrated states, for drawing.
    """

    def __init__(self, root: np.ndarray, n_params: int, capacity: int = 256, n_inputs: int = 1):
        n = root.shape[0]
        self.n_nodes = 0
        self.states = np.empty((capacity, n))
        self.parents = np.empty(capacity, dtype=np.int64)
        self.costates = np.full((capacity, n), np.nan)
        self.controls = np.full((capacity, n_inputs), np.nan)
        self.params = np.full((capacity, n_params), np.nan)
        self.durations = np.empty(capacity)
        self.costs = np.empty(capacity)
        self.max_abs_u = np.empty(capacity)
        self.trajectories: list[np.ndarray] = []
        # the strategy that made a node's edge where it is not told by the edge itself (a
        # goal connection's, a shortcut's): `kind`
        self.made_by: dict[int, str] = {}
        self._cost_to_come = np.zeros(0)  # `cost_to_come`'s rows so far
        self.add(root, -1, np.full(n, np.nan), np.full(n_params, np.nan), 0.0, 0.0, root[None],
                 0.0)

    def _grow(self) -> None:
        for name in ("states", "parents", "costates", "controls", "params", "durations",
                     "costs", "max_abs_u"):
            old = getattr(self, name)
            new = np.full((2 * old.shape[0], *old.shape[1:]), np.nan, dtype=old.dtype) \
                if name in _NAN_FILLED else np.empty((2 * old.shape[0], *old.shape[1:]),
                                                     dtype=old.dtype)
            new[: self.n_nodes] = old[: self.n_nodes]
            setattr(self, name, new)

    def reserve(self, k: int) -> None:
        """Room for ``k`` more nodes, for a compiled caller that writes them in place (rows
        not written hold NaN in ``controls``, ``costates`` and ``params``)."""
        while self.states.shape[0] < self.n_nodes + k:
            self._grow()

    def add(self, state, parent, costate, params, duration, cost, trajectory,
            max_abs_u, control=None) -> int:
        if self.n_nodes == self.states.shape[0]:
            self._grow()
        i = self.n_nodes
        # always written: a compiled batch writes its draws' rows in place, and a row it
        # wrote but did not keep would otherwise hand its held input to this edge
        self.controls[i] = np.nan if control is None else control
        self.states[i] = state
        self.parents[i] = parent
        self.costates[i] = costate
        self.params[i] = params
        self.durations[i] = duration
        self.costs[i] = cost
        self.max_abs_u[i] = max_abs_u
        self.trajectories.append(trajectory)
        self.n_nodes += 1
        return i

    def kind(self, i: int) -> str:
        """What made node ``i``'s edge: the connection or shortcut recorded in ``made_by``,
        else "learned" (an extremal: it has a costate) or "control" (a held input)."""
        if i in self.made_by:
            return self.made_by[i]
        return "control" if np.isnan(self.costates[i]).any() else "learned"

    def cost_to_come(self, nodes: np.ndarray) -> np.ndarray:
        """(k,) the cost of the tree's path from the root to each of ``nodes`` (k,): the sum
        of its edges' ``costs``. Kept for every node so far and extended by the nodes added
        since (a parent precedes its children, and an edge is not changed once the next
        call has seen it)."""
        done, total = len(self._cost_to_come), self.n_nodes
        if done < total:
            ctc = np.empty(total)
            ctc[:done] = self._cost_to_come
            parents, costs = self.parents[:total].tolist(), self.costs[:total].tolist()
            for i in range(done, total):  # sequential: a child's sum needs its parent's
                ctc[i] = 0.0 if parents[i] < 0 else ctc[parents[i]] + costs[i]
            self._cost_to_come = ctc
        return self._cost_to_come[nodes]

    def path_to(self, node: int) -> list[int]:
        """Node indices from the root to ``node``."""
        path = []
        while node >= 0:
            path.append(node)
            node = int(self.parents[node])
        return path[::-1]


@dataclass
class Plan:
    """What a planning query returns; ``to_dict`` is the plan-file content."""

    system: str
    start: np.ndarray
    goal: np.ndarray
    goal_tolerance: float
    time_weight: float
    dt: float
    status: str  # "exact", "approximate" or "timeout"
    planning_time_s: float
    planning_cpu_s: float
    iterations: int
    tree: PlannerData
    path_nodes: list[int] = field(default_factory=list)
    u_max: float | None = None  # truncation bound (unconstrained extremals cut at |u| = u_max)
    obstacles: list[dict] = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    goal_angles: tuple[int, ...] = ()  # angle coordinates compared modulo a turn at the goal
    # (m,) input box of a saturated system: every edge's u* = clip(-R^-1 B^T lambda, low, high)
    input_low: np.ndarray | None = None
    input_high: np.ndarray | None = None
    # the path end's distance to the goal region as the planner's goal test measured it
    # (weighted or a user goal function); None: the plain distance to ``goal``
    end_goal_distance: float | None = None
    # how the goal was tested (`PlanningProblem.goal_test`); None: not recorded
    goal_test: str | None = None
    # states in the planner's own graph when ``tree`` holds the path only (a peer whose graph
    # is not ours, e.g. OMPL's PlannerData); None: the tree's nodes
    graph_states: int | None = None

    @property
    def limit_mode(self) -> str | None:
        """"saturate" (Pontryagin over the input box), "truncate" or None (unbounded)."""
        if self.input_low is not None:
            return "saturate"
        return "truncate" if self.u_max is not None else None

    @property
    def symmetric_limit(self) -> float | None:
        """The single bound |u_i| <= u for every input, if the limits are of that form."""
        if self.input_low is None:
            return self.u_max
        lo, hi = np.asarray(self.input_low), np.asarray(self.input_high)
        if np.all(hi == hi[0]) and np.array_equal(-lo, hi) and np.isfinite(hi[0]):
            return float(hi[0])
        return None

    @property
    def solved(self) -> bool:
        return self.status == "exact"

    @property
    def nodes(self) -> int:
        """States in the planner's graph (the tree's nodes unless ``graph_states`` says)."""
        return self.tree.n_nodes if self.graph_states is None else int(self.graph_states)

    @property
    def path_cost(self) -> float:
        return float(sum(self.tree.costs[i] for i in self.path_nodes[1:]))

    @property
    def max_abs_u(self) -> float:
        """Largest |u| along the path."""
        return float(max((self.tree.max_abs_u[i] for i in self.path_nodes[1:]), default=0.0))

    @property
    def path_duration(self) -> float:
        return float(sum(self.tree.durations[i] for i in self.path_nodes[1:]))

    @property
    def duration_by(self) -> dict[str, float]:
        """The share of the path's duration made by each kind of edge (`PlannerData.kind`:
        "learned", "control", or the connection's name: "shooting", "funnel", "lqr"),
        largest first; empty for a path without duration."""
        total = self.path_duration
        if not total > 0:
            return {}
        out: dict[str, float] = {}
        for i in self.path_nodes[1:]:
            k = self.tree.kind(i)
            out[k] = out.get(k, 0.0) + float(self.tree.durations[i])
        return {k: v / total for k, v in sorted(out.items(), key=lambda kv: -kv[1])}

    @property
    def final_goal_distance(self) -> float | None:
        """Distance of the path's end to the goal (angles in ``goal_angles`` modulo a turn), or
        to the goal region of the planner's goal test."""
        if not self.path_nodes:
            return None
        if self.end_goal_distance is not None:
            return float(self.end_goal_distance)
        diff = self.tree.states[self.path_nodes[-1]] - self.goal
        for j in self.goal_angles:
            diff[j] = (diff[j] + np.pi) % (2.0 * np.pi) - np.pi
        return float(np.linalg.norm(diff))

    def edges(self) -> list[dict]:
        """The path's edges: an extremal edge has ``costate`` and ``params`` (``control``
        null), a control edge the constant ``control`` (``costate`` and ``params`` null)."""
        t = self.tree

        def listed(a: np.ndarray) -> list[float] | None:
            return None if np.isnan(a).all() else a.tolist()

        return [
            {
                "from": t.states[t.parents[i]].tolist(),
                "to": t.states[i].tolist(),
                "costate": listed(t.costates[i]),
                "params": listed(t.params[i]),
                "control": listed(t.controls[i]),
                "duration": float(t.durations[i]),
                "cost": float(t.costs[i]),
                "max_abs_u": float(t.max_abs_u[i]),
            }
            for i in self.path_nodes[1:]
        ]

    def to_dict(self) -> dict:
        t = self.tree
        n = t.n_nodes
        return {
            "system": self.system,
            "start": self.start.tolist(),
            "goal": self.goal.tolist(),
            "goal_tolerance": self.goal_tolerance,
            "time_weight": self.time_weight,
            "dt": self.dt,
            "solved": self.solved,
            "status": self.status,
            "planning_time_s": self.planning_time_s,
            "planning_cpu_s": self.planning_cpu_s,
            "iterations": self.iterations,
            "nodes": self.nodes,
            "path_cost": self.path_cost,
            "path_duration": self.path_duration,
            "u_max": self.symmetric_limit,
            "limit_mode": self.limit_mode,
            "input_low": _finite_or_none(self.input_low),
            "input_high": _finite_or_none(self.input_high),
            "max_abs_u": self.max_abs_u,
            "obstacles": self.obstacles,
            "goal_angles": list(self.goal_angles),
            "goal_test": self.goal_test,
            "final_goal_distance": self.final_goal_distance,
            **self.extra,
            "path": self.edges(),
            "tree": {"states": t.states[:n].tolist(), "parents": t.parents[:n].tolist()},
        }


def _finite_or_none(a: np.ndarray | None) -> list[float | None] | None:
    """A JSON-safe list: unbounded (infinite) entries as null."""
    if a is None:
        return None
    return [float(v) if np.isfinite(v) else None for v in np.asarray(a, dtype=float)]
