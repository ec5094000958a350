"""What the planner's loop and its strategies share: the edge record, the growing tree, the
loop's progress counters, and the two small protocols the loop knows its strategies by.

- a `Steering` strategy proposes an edge toward a target (OMPL's ``DirectedControlSampler``:
  ``sampleTo``): the learned steering (`planning.learned`), random controls
  (`planning.controls`);
- a `Connection` strategy tries to finish, from the tree into the goal region: shooting, the
  goal funnel, the LQR loop (`planning.connections`), or one of your own.

docs/architecture.md draws the loop around them; `planning.schedule` says when each is on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np

from rrtcolearn.planning.nearest import NodeIndex
from rrtcolearn.planning.tree import PlannerData

# what became of an iteration: no node within reach of the target, V rejected every
# (node, target) query, or the draw gave no edge (why), or an edge was added
OUTCOMES = ("added", "out_of_reach", "invalid_query", "no_costate", "input_limit",
            "state_box", "obstacle", "nonfinite")


class Edge(NamedTuple):
    """One tree edge from its parent's state.

    traj : (steps + 1, .) the integrated states from the parent's (columns 0..n-1); an
        extremal's rows also hold its costate (n..2n-1) and its cost so far (2n).
    steps, cost, u_abs : its RK4 steps, its cost and its largest |u_i|.
    hit : it ends in the goal region.
    params, costate : an extremal's steering parameters (with its duration last) and its
        costate at the start; None for a random-control edge.
    control : a random-control edge's held input; None for an extremal.
    end_distance : the end's distance to the goal region, where known.
    """

    traj: np.ndarray
    steps: int
    cost: float
    u_abs: float
    hit: bool
    params: np.ndarray | None = None
    costate: np.ndarray | None = None
    control: np.ndarray | None = None
    end_distance: float | None = None


def grown(a: np.ndarray, m: int, fill) -> np.ndarray:
    """``a`` with at least ``m`` rows: new rows (as many as it had plus ``m``) set to ``fill``."""
    if a.shape[0] >= m:
        return a
    return np.concatenate([a, np.full((a.shape[0] + m, *a.shape[1:]), fill, dtype=a.dtype)])


def add_edge(tree: PlannerData, parent: int, edge: Edge, dt: float) -> int:
    """Add the node at the end of ``edge`` below ``parent`` to ``tree`` (an extremal with its
    costate and parameters, a held input with its control); its index."""
    n = tree.states.shape[1]
    end = edge.traj[-1, :n]
    if edge.control is not None:
        return tree.add(end, parent, np.full(n, np.nan), np.full(tree.params.shape[1], np.nan),
                        edge.steps * dt, edge.cost, edge.traj, edge.u_abs,
                        control=edge.control)
    return tree.add(end, parent, edge.costate, edge.params[:-1], edge.steps * dt, edge.cost,
                    edge.traj[:, :n], edge.u_abs)


@dataclass
class GrowingTree:
    """The tree of one solve with what finds its nodes: ``plain`` (weighted distance) and
    ``wrapped`` (angles modulo a turn; ``plain`` itself without angles) nearest-node indices,
    ``weight`` the planner metric's coordinate weights, and per node ``shifts``, the whole
    turns that take its state into the box (the learning query's start)."""

    data: PlannerData
    weight: np.ndarray
    plain: NodeIndex
    wrapped: NodeIndex
    shifts: np.ndarray
    wrap_shift: Callable[[np.ndarray], np.ndarray]  # the system's: states -> shifts (N, n)
    dt: float

    @property
    def indices(self) -> tuple[NodeIndex, ...]:
        """The distinct node indices, each kept up to date as nodes are added."""
        return (self.plain, self.wrapped) if self.wrapped is not self.plain else (self.plain,)

    @property
    def states(self) -> np.ndarray:
        """(nodes, n) the nodes' states."""
        return self.data.states[: self.data.n_nodes]

    def add(self, parent: int, edge: Edge) -> int:
        """Add ``edge``'s end below ``parent``: to the tree data, the indices and the shifts."""
        n = self.data.states.shape[1]
        end = edge.traj[-1, :n]
        for index in self.indices:
            index.add(end)
        node = add_edge(self.data, parent, edge, self.dt)
        if node == self.shifts.shape[0]:
            self.shifts = np.concatenate([self.shifts, np.empty_like(self.shifts)])
        self.shifts[node] = self.wrap_shift(edge.traj[-1:, :n])[0]
        return node


@dataclass
class Progress:
    """The loop's counters of one solve (the compiled random-control batch keeps them too)."""

    best_goal: float  # the nearest any node came to the goal region
    iterations: int = 0
    goal_node: int = -1
    connection: str | None = None  # which connection made the last edge, if one did
    since_nearer: int = 0  # goal-biased iterations since a node came nearer the goal
    since_growth_nearer: int = 0  # iterations since a node came nearer the goal
    last_growth: int = 0  # the iteration that last added a node
    stalled: bool = False
    edges_by: dict = field(default_factory=lambda: {"learned": 0, "control": 0})
    outcomes: dict = field(default_factory=lambda: dict.fromkeys(OUTCOMES, 0))


class Steering(Protocol):
    """A way to grow the tree toward a target.

    ``steer`` returns (parent, edge): the node it expands and the edge from it, or edge None
    with ``rejected`` naming why (one of `OUTCOMES`; None: nothing to count, the expansion
    was left to a later call). It may draw random numbers; it must not add the edge (the
    loop does)."""

    kind: str  # the plan's edges_by key
    rejected: str | None

    def steer(self, rng: np.random.Generator, tree: GrowingTree, target: np.ndarray,
              to_goal: bool) -> tuple[int, Edge | None]: ...


class Connection(Protocol):
    """A way to finish: from a node of the tree into the goal region.

    ``connect`` returns (node, edges): the chain of edges from that node whose last ends in
    the goal region, or None. It is asked at every goal-biased iteration while it is on, and
    keeps what it needs between calls (e.g. which nodes it has tried). ``report`` is what the
    plan's ``extra`` records of it."""

    name: str

    def connect(self, tree: GrowingTree) -> tuple[int, list[Edge]] | None: ...

    def report(self) -> dict: ...
