"""Configuration: pydantic models (unknown keys rejected), TOML in, resolved TOML out.

Defaults reproduce the paper's pendulum experiment; where the paper is silent the choice is
documented in docs/configuration.md and docs/method.md (goal bias, validity threshold).
"""

from __future__ import annotations

import copy
import difflib
import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin

import tomli_w
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from rrtcolearn.errors import ConfigError


def _takes(annotation: Any, kind: type) -> bool:
    """Whether a field's type admits values of ``kind`` as written (bool or str): the type
    itself, a Literal of such values, or a union or list holding one."""
    if annotation is kind:
        return True
    args = get_args(annotation)
    if get_origin(annotation) is Literal:
        return any(isinstance(a, kind) for a in args)
    return any(_takes(a, kind) for a in args)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    @model_validator(mode="before")
    @classmethod
    def _as_written(cls, data: Any) -> Any:
        # pydantic reads true/false as 1/0 and "2.8" as 2.8 where a number is expected: a
        # mistyped setting would pass silently (plan.goal_bias=true is a goal bias of 1)
        if isinstance(data, dict):
            for key, v in data.items():
                field = cls.model_fields.get(key)
                if field is None:
                    continue
                values = v if isinstance(v, list) else [v]
                for kind, what in ((bool, "true/false"), (str, "text")):
                    if any(isinstance(x, kind) for x in values) and \
                            not _takes(field.annotation, kind):
                        raise ValueError(f"{key}: must be a number, not {what} ({v!r})")
        return data

    @field_validator("*", mode="after")
    @classmethod
    def _finite(cls, v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError("must be a finite number")
        if isinstance(v, list) and any(isinstance(x, float) and not math.isfinite(x) for x in v):
            raise ValueError("must contain finite numbers only")
        return v


class SystemConfig(_Section):
    name: str = "pendulum"
    input_scale: list[float] | None = Field(
        None, description="weights of the state coordinates in learning distances (default: "
        "2*pi / sampling range, all 1 for the pendulum)")
    time_weight: float = Field(1.0, gt=0, description="w in the running cost w + u^2/2")
    u_max: float | list[float] | None = Field(
        None, description="input limit |u_i| <= u_max (one value, or one per input; none: "
        "the system's own limits, unbounded for the paper's pendulum)")
    u_low: list[float] | None = Field(
        None, description="asymmetric input limits u_low <= u <= u_high, one per input "
        "(instead of u_max)")
    u_high: list[float] | None = None
    limit_mode: Literal["saturate", "truncate"] = Field(
        "saturate", description="how limits enter: Pontryagin over the input box (saturated "
        "optimal control, every extremal feasible) or unconstrained extremals truncated at "
        "their first violation (scalar u_max only; kept for comparison)")

    @model_validator(mode="after")
    def _limits(self) -> SystemConfig:
        umax = self.u_max
        values = [] if umax is None else (umax if isinstance(umax, list) else [umax])
        if any(not v > 0 for v in values) or (isinstance(umax, list) and not umax):
            raise ValueError(f"u_max must be positive (one value, or one per input), got "
                             f"{umax!r}")
        if umax is not None and (self.u_low is not None or self.u_high is not None):
            raise ValueError("give either u_max or u_low/u_high, not both")
        if (self.u_low is None) != (self.u_high is None):
            raise ValueError("u_low and u_high go together (use -inf/inf as large numbers, "
                             "e.g. -1e9, for an unbounded side)")
        if self.u_low is not None:
            if len(self.u_low) != len(self.u_high) or any(
                    lo >= hi for lo, hi in zip(self.u_low, self.u_high, strict=False)):
                raise ValueError("u_low and u_high need one value per input with u_low < u_high")
        if self.limit_mode == "truncate" and (self.u_low is not None
                                              or isinstance(umax, list)):
            raise ValueError("limit_mode = 'truncate' supports a single symmetric u_max only")
        return self

    def input_bounds(self) -> tuple[list[float], list[float]] | None:
        """The configured (low, high) input limits, or None when the config sets none."""
        if self.u_low is not None:
            return list(self.u_low), list(self.u_high)
        if self.u_max is None:
            return None
        umax = self.u_max if isinstance(self.u_max, list) else [self.u_max]
        return [-v for v in umax], list(umax)

    @property
    def truncation_limit(self) -> float | None:
        """The |u| bound at which unconstrained extremals are cut (limit_mode 'truncate')."""
        return float(self.u_max) if self.limit_mode == "truncate" and self.u_max is not None \
            else None


class GenerateConfig(_Section):
    n_simulations: int | None = Field(
        None, ge=1, description="simulations per epoch (Alg. 2); none: derived from the "
        "state dimension (the paper's 40 000 for two states)")
    offline_budget: float | None = Field(
        None, gt=0, description="with n_simulations left to the library: choose it by a "
        "convergence test on held-out J error (doubling the data until the error improves "
        "by less than 10%) within this many CPU seconds; none: by the state dimension")
    dt: float = Field(0.01, gt=0, le=1.0, description="RK4 step (s)")
    max_cost: float | None = Field(
        None, gt=0, description="stop a simulation when its cost exceeds this (none: "
        "derived, the 90% quantile of the cost at which pilot simulations leave the reach "
        "ball; 4.5 for the paper's pendulum, whose bound is 2)")
    max_state_distance: float = Field(1.5, gt=0,
                                      description="... or when |x(t) - x0| exceeds this")
    max_duration: float = Field(20.0, gt=0, le=1000.0,
                                description="longest segment (s); bounds memory and time")
    chunk_size: int = Field(2000, ge=1, le=100_000, description="simulations per seeded chunk")
    goal_simulations: int = Field(0, ge=0, le=1_000_000, description=(
        "simulations run backwards in time from the query's goal: data points that end "
        "exactly there (they crowd Alg. 3's neighbour lists near the goal: keep to a few "
        "thousand)"))
    colearn_rounds: int = Field(0, ge=0, le=50, description=(
        "after the uniform data, up to this many co-learning rounds of n_simulations / 10 "
        "simulations each, aimed at the (x0, x1) pairs the learned steering fails on "
        "(docs/colearn.md); 0: off"))
    state_low: list[float] | None = Field(None, description="override the start-state box")
    state_high: list[float] | None = None
    param_low: list[float] | None = Field(None, description="override the costate-parameter range")
    param_high: list[float] | None = None


class CleanConfig(_Section):
    d: float = Field(0.05, gt=0, description="cleaning radius (Alg. 3)")
    k_max: int = Field(5000, ge=1, description="stop after this many draws without removal")
    method: Literal["randomized", "greedy"] = "randomized"


class LearnConfig(_Section):
    n_neighbors: int = Field(3, ge=1, description="m, neighbours averaged by k-NN")
    cost_lower: float = Field(1e-5, gt=0, description="saturation of the learned cost-to-go")
    cost_upper: float = Field(1e5, gt=0)
    validity_threshold: float | None = Field(
        None, gt=0, description="max summed distance to the m neighbours (none: derived, "
        "the 97% quantile of held-out valid pairs; the paper's 0.5 is the 96.6% quantile "
        "on its pendulum data)")
    periodic: bool = Field(True, description="angle coordinates wrap around in the distance "
                           "(rows near the seam are indexed one turn over too)")
    learner: Literal["knn", "mlp"] | None = Field(
        None, description="J and U from k-NN (the paper) or from a neural network (V stays "
        "k-NN); mlp needs the optional scikit-learn dependency; none: k-NN up to two "
        "states, mlp above")
    steering: Literal["mean", "local_linear"] = Field(
        "mean", description="U from the k-NN: the m neighbours' mean (the paper) or a local "
        "linear fit over 4 neighbours per feature (better on the shipped cart-pole and the "
        "acrobot, worse on sparse_rrt's cart-pole and the pendulum: docs/predictors.md)")
    mlp_hidden: list[int] = Field([64, 64, 64], min_length=1, max_length=8,
                                  description="hidden layer widths of the mlp learner")
    mlp_max_iter: int = Field(200, ge=1, le=10_000, description="training epochs at most")
    mlp_max_samples: int | None = Field(100_000, ge=20,
                                        description="rows the networks train on (None: all)")

    @model_validator(mode="after")
    def _widths(self) -> LearnConfig:
        if any(h < 1 or h > 4096 for h in self.mlp_hidden):
            raise ValueError("mlp_hidden widths must lie in 1..4096")
        return self


class BoxObstacle(_Section):
    """Forbidden box low <= x <= high in state space."""

    type: Literal["box"] = "box"
    low: list[float]
    high: list[float]

    @model_validator(mode="after")
    def _ordered(self) -> BoxObstacle:
        if len(self.low) != len(self.high):
            raise ValueError("low and high need the same number of values")
        if any(lo > hi for lo, hi in zip(self.low, self.high, strict=True)):
            raise ValueError("low must not exceed high")
        return self


class HalfPlaneObstacle(_Section):
    """Forbidden half-space normal . x > offset."""

    type: Literal["halfplane"] = "halfplane"
    normal: list[float]
    offset: float


class _ShapeKeys(_Section):
    """The keys of a workspace shape (rrtcolearn.geometry), checked there."""

    shape: Literal["box", "disc", "polygon", "sphere"]
    center: list[float] | None = None
    size: list[float] | None = None
    angle: float | None = None
    radius: float | None = None
    vertices: list[list[float]] | None = None

    def spec(self) -> dict[str, Any]:
        """The keys given, as rrtcolearn.geometry reads them."""
        return {k: v for k, v in self.model_dump().items() if v is not None and k != "type"}


class ShapeObstacle(_ShapeKeys):
    """Forbidden shape in workspace coordinates, which plan.body must not touch: a box
    (center, size[, angle]), disc (center, radius), convex polygon (vertices) or sphere."""

    type: Literal["shape"] = "shape"

    @model_validator(mode="after")
    def _valid(self) -> ShapeObstacle:
        from rrtcolearn.geometry import shape_from_dict
        shape_from_dict(self.spec())
        return self


class BodyConfig(_ShapeKeys):
    """The robot's body: a shape in its own frame (box size, disc radius, ...) and ``pose``,
    the state indices placing it: [ix, iy] or [ix, iy, itheta] (planar), [ix, iy, iz] (3-D);
    or links: ``shapes`` (a list of shapes) placed by ``fk``, the ``module:attribute`` name
    of a forward-kinematics function (states (N, n) -> poses (N, links, 3))."""

    shape: Literal["box", "disc", "polygon", "sphere"] | None = None
    shapes: list[dict[str, Any]] | None = None
    pose: list[int] | None = None
    fk: str | None = None

    @model_validator(mode="after")
    def _valid(self) -> BodyConfig:
        from rrtcolearn.geometry import Body
        Body.from_dict(self.spec())
        return self


def _obstacle_kind(value: Any) -> str | None:
    # workspace shapes are written with `shape = ...`; state-space ones with `type = ...`
    if isinstance(value, dict):
        return "shape" if "shape" in value else value.get("type")
    return getattr(value, "type", None)


ObstacleConfig = Annotated[
    Annotated[BoxObstacle, Tag("box")] | Annotated[HalfPlaneObstacle, Tag("halfplane")]
    | Annotated[ShapeObstacle, Tag("shape")],
    Discriminator(_obstacle_kind, custom_error_type="obstacle_kind",
                  custom_error_message="an obstacle needs type = 'box' or 'halfplane' "
                  "(state space) or shape = 'box', 'disc', 'polygon' or 'sphere' (workspace)")]


class PlanConfig(_Section):
    start: list[float] | None = Field(None, description="default: the system's (pendulum: "
                                      "[-pi, 0])")
    goal: list[float] | None = Field(None, description="default: the system's (pendulum: [0, 0])")
    goal_tolerance: float = Field(0.1, gt=0)
    goal_weights: list[float] | None = Field(
        None, description="weights of the state coordinates in the goal test, one per state "
        "(0: a free coordinate, e.g. [1, 1, 0, 0] for angles only); none: all 1")
    wrap_goal: bool = Field(False, description="compare angles modulo a turn in the goal test "
                            "(the paper compares plain coordinates)")
    state_low: list[float] | None = Field(
        None, description="state constraints for the planner: an edge leaving them is "
        "invalid (one value per state, entries of angle coordinates ignored; none: the "
        "sampling box); they may differ from generate.state_low, where the data's start "
        "states are drawn")
    state_high: list[float] | None = None
    goal_bias: float = Field(0.2, ge=0, le=1, description="share of iterations whose target "
                             "is the goal (the paper does not state it)")
    sigma: float | None = Field(None, gt=0, description="steering noise around U's "
                                "prediction; none: 1/8 of the parameters' mean range (the "
                                "paper's pi/4)")
    sigma_goal: float | None = Field(None, gt=0, description="the same towards the goal; "
                                     "none: 1/4 of the range (the paper's pi/2)")
    decimals: int = Field(2, ge=0, le=12, description="steering parameters are rounded to "
                          "this many decimals (the paper's Section 5.1)")
    time_limit: float | None = Field(10.0, gt=0)
    max_iterations: int | None = Field(None, ge=1)
    anytime: bool = Field(
        False, description="spend the whole time (or iteration) limit: after the first "
        "solution solve again with fresh child seeds, shortcut every path (stretches by "
        "single extremals, the tail to the goal by exact extremals or the LQR loop), draw "
        "later solves' random controls from an input box narrowed after each cheaper solve "
        "(where the box's dearest input costs more than the time weight), and "
        "return the cheapest path, its best cost "
        "against CPU in the plan's extra.anytime.progress (rrtcolearn.anytime, "
        "rrtcolearn.planning.improve)")
    polish: bool = Field(
        False, description="after the first solution (without anytime), one improvement "
        "round before returning: multiple shooting of the whole path, then shortcuts, each "
        "within a quarter of the solve's iterations in improvement steps (deterministic); "
        "the raw and polished costs in the plan's extra.polish. Off by default: it costs "
        "1.5-12.5x the first solve's CPU (docs/anytime.md, 'Polishing the first solution')")
    obstacles: list[ObstacleConfig] = Field(
        default_factory=list, description="state-space regions (type = 'box', 'halfplane') "
        "and workspace shapes the body must not touch (shape = 'box', 'disc', 'polygon', "
        "'sphere'; rrtcolearn.geometry)")
    body: BodyConfig | None = Field(
        None, description="the robot's body among the workspace shapes: a shape and the "
        "state indices of its pose, e.g. shape = 'box', size = [0.5, 0.25], pose = [0, 1, 2]")
    extend_distance: float | None = Field(
        None, ge=0, description="move random targets to within this (weighted) distance of "
        "their nearest node; 0: off, the paper's planner; none: derived (off where random "
        "targets often lie within the data's reach, else a third of the reach)")
    control_samples: int | None = Field(
        None, ge=1, le=1000, description="steering draws per iteration, the one ending "
        "nearest the target kept; 1: the paper's planner; none: 1 with one steering "
        "parameter, 16 with more")
    refine_iterations: int = Field(
        0, ge=0, le=50, description="Newton iterations (on the costate and duration) that "
        "make a learned edge that came halfway to its aim land on it; 0: off, the paper's "
        "planner. 6 lowered the pendulum's first-path cost by 7% at 1.25-1.5x its planning "
        "CPU on the paper's model (docs/landing.md)")
    edge_cost_ratio: Annotated[float, Field(ge=0)] | Literal["data"] = Field(
        0.0, description="the learned steering keeps its nearest draw whose "
        "re-simulated cost is at most this multiple of the learned J (the lesser of J "
        "between the edge's ends and J from its start to its aim), else U's guess itself if "
        "that is within it, else no edge; 0: off, the paper's planner; \"data\": derived from "
        "the data, the 99% quantile of its segments' costs over J from their other neighbours "
        "(1.3-2.3 on the bench models). Off by default: on the acrobot and cart-pole it did "
        "not lower the first or the 10-s cost beyond the seeds' spread and cost up to 2.4x "
        "the CPU (docs/ablation.md)")
    parent_cost_to_come: bool = Field(
        False, description="the learned steering's parent: the candidate with the least "
        "cost-to-come plus predicted J to the target (RRT*'s choose-parent) instead of the "
        "least J alone (the paper's); cheaper first paths where learned edges carry them, "
        "slower where random controls do (docs/ablation.md)")
    goal_parent_tries: int = Field(
        4, ge=0, le=100, description="when a solve reaches the goal, shoot at the goal from "
        "at most this many nodes whose cost-to-come plus the learned J to the goal is below "
        "the path's cost (least first, V-valid, from U's guess), keeping the cheapest path "
        "(RRT*'s choose-parent for the goal); where the goal funnel is on, then as many "
        "continuations from nodes within its radius, then as many within twice it, "
        "cheapest cost-to-come plus funnel cost-to-go first; 0: off, the paper's planner. "
        "Pendulum first cost 2.31x -> 1.53x the optimum (median, 20 seeds) at 1.04-1.08x the "
        "CPU per seed; through the funnel cart-pole 5.35x -> 4.34x, acrobot 8.17x -> 6.38x "
        "(docs/ablation.md)")
    max_candidates: int | None = Field(
        32, ge=1, description="query J for only this many nodes nearest the target "
        "(weighted distance, from the tree's nearest-neighbour index), so an iteration's "
        "cost does not grow with the tree; none: every node within reach, the paper's "
        "planner")
    goal_connect: bool | None = Field(
        None, description="in goal-biased iterations, also steer exactly to the goal by "
        "shooting from U's guess (nearest untried node within the data's reach); false: the "
        "paper's planner; none: switched on by the planner once the learned steering stalls "
        "near the goal (50 goal-biased iterations without a node nearer the goal)")
    connect_reach: float | None = Field(
        None, gt=0, description="goal connection only from nodes within this weighted "
        "distance of the goal; none: the data's reach (generate.max_state_distance)")
    goal_funnel: int | None = Field(
        None, ge=0, le=1_000_000, description="extremals integrated backwards from the goal "
        "at the start of each plan; in goal-biased iterations the node nearest one of their "
        "states is steered to the goal along it (continuation, then shooting); 0: the "
        "paper's planner; none: built by the planner when it switches shooting on, 2 500 "
        "of them doubling up to 20 000 while no tree node is near it")
    funnel_radius: float = Field(
        0.3, gt=0, description="funnel connection only from nodes within this weighted "
        "distance of a funnel state")
    funnel_duration: float | None = Field(
        None, gt=0, le=1000, description="the funnel's extremals are integrated for at most this "
        "long (s); their cost is bounded by generate.max_cost; none: the data's longest "
        "extremal (generate.max_duration as fitted), as long as U and J know them, or where "
        "the goal has no LQR connection until they leave the state box, for at most "
        "generate.max_duration, with no cost bound")
    funnel_min_duration: float = Field(
        0.0, ge=0, le=100, description="funnel states less than this time (s) from the goal "
        "are dropped (where the boundary value problem from near them is ill-conditioned)")
    control_edges: bool | None = Field(
        None, description="random-control expansion (OMPL's and sparse_rrt's: an input "
        "uniform in the input box held for a random time) for a system with input limits: "
        "true: ordinary targets are expanded by it and goal targets by the learned steering "
        "while a node lies within the data's reach of them; false: the paper's planner "
        "(learned steering only); none: switched on once the learned steering stalls (30 "
        "iterations without a node nearer the goal)")
    goal_lqr: bool | None = Field(
        None, description="in goal-biased iterations, also steer to the goal by LQR about an "
        "equilibrium next to the goal (input in the input box, within half the tolerance): "
        "the untried node with the least LQR cost-to-go follows the saturated closed loop, "
        "added as constant-input edges; false: the paper's planner; none: switched on once "
        "the tree stalls near the goal (50 goal-biased iterations without a node nearer "
        "the goal), also while random controls explore; off where the goal is no "
        "equilibrium")
    stall_iterations: int = Field(
        10_000, ge=0, description="stop early when this many iterations in a row added no "
        "node, with a diagnosis of what rejected them (0: never)")
    input_limit: Literal["reject", "cut"] = Field(
        "reject", description="with system.limit_mode = 'truncate': an edge whose input "
        "exceeds u_max is rejected, or cut before it")

    @model_validator(mode="after")
    def _workspace(self) -> PlanConfig:
        plan_obstacles(self)  # shapes and body agree (2-D or 3-D); a shape needs the body
        return self


def plan_obstacles(plan: PlanConfig) -> list[dict[str, Any]]:
    """plan.obstacles as the planner reads them: the state-space ones, and the workspace
    shapes with plan.body as one obstacle {type = 'workspace', body, shapes}."""
    from rrtcolearn.geometry import Workspace
    shapes = [o.spec() for o in plan.obstacles if isinstance(o, ShapeObstacle)]
    out = [o.model_dump() for o in plan.obstacles if not isinstance(o, ShapeObstacle)]
    if shapes and plan.body is None:
        raise ValueError("body: workspace obstacles (shape = ...) need the robot's body, "
                         "e.g. [plan.body] shape = 'box', size = [0.5, 0.25], pose = [0, 1, 2]")
    if shapes:
        spec = {"type": "workspace", "body": plan.body.spec(), "shapes": shapes}
        try:
            Workspace.from_dict(spec)
        except ValueError as exc:
            raise ValueError(f"obstacles: {exc}") from None
        out.append(spec)
    return out


class ProblemSpec(_Section):
    """One planning problem of the experiment: a torque limit, time weight and tolerance."""

    name: str
    u_max: float | None = Field(None, gt=0)
    time_weight: float = Field(1.0, gt=0)
    goal_tolerance: float = Field(0.1, gt=0)


def pendulum_problems() -> list[ProblemSpec]:
    """The pendulum experiment's five problems (the paper's unbounded swing-up, and torque
    limits with two tolerances and time weights)."""
    return [
        ProblemSpec(name="unbounded-tol0.1"),
        ProblemSpec(name="u2-tol0.1", u_max=2.0),
        ProblemSpec(name="u2-tol0.2", u_max=2.0, goal_tolerance=0.2),
        ProblemSpec(name="u1-tol0.1", u_max=1.0, time_weight=0.1),
        ProblemSpec(name="u1-tol0.2", u_max=1.0, time_weight=0.1, goal_tolerance=0.2),
    ]


class ExperimentConfig(_Section):
    """The paper's protocol (epochs x runs) and the peers run beside it."""

    epochs: int = Field(10, ge=1)
    runs_per_epoch: int = Field(300, ge=1)
    peer_runs_per_epoch: int | None = Field(
        None, ge=1, description="runs per epoch for the peers (default: runs_per_epoch)")
    direct_runs_per_epoch: int = Field(10, ge=0, description="runs of the slow direct method")
    direct_pairs: int = Field(3000, ge=10, description="collocation pairs per direct dataset")
    planners: list[str] = Field(default_factory=lambda: [
        "rrtcolearn", "random-rrt", "ompl-RRT", "ompl-KPIECE1", "ompl-EST", "direct"])
    problems: list[ProblemSpec] | None = Field(
        None, description="the problems (none: the pendulum's five, pendulum_problems, or for "
        "another system its standard query as the one problem 'standard')")
    peer_u_max: float | None = Field(
        None, gt=0, description="input bound of the random-control peers (random-rrt, "
        "ompl-*) on problems whose inputs are unbounded; none: they skip such problems")
    time_limit: float = Field(10.0, gt=0)
    cpu_time_limit: float | None = Field(
        None, gt=0, description="also stop after this many CPU seconds of the planning "
        "process: every planner gets the same CPU on a loaded machine")
    max_iterations: int | None = Field(
        None, ge=1, description="also stop after this many iterations (every planner that counts "
        "iterations; OMPL's bindings count none): a limit that does not depend on the "
        "machine's load")
    runs_per_task: int = Field(10, ge=1, description="planning runs per parallel task")
    d_grid: list[float] = Field(default_factory=lambda: [0.01, 0.02, 0.05, 0.1, 0.2])
    d_grid_plans: int = Field(30, ge=1, description="planning runs per d in the grid search")
    held_out_simulations: int = Field(2000, ge=10)


class Config(_Section):
    name: str = Field("pendulum-swingup", pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    seed: int = Field(0, ge=0)
    system: SystemConfig = Field(default_factory=SystemConfig)
    generate: GenerateConfig = Field(default_factory=GenerateConfig)
    clean: CleanConfig = Field(default_factory=CleanConfig)
    learn: LearnConfig = Field(default_factory=LearnConfig)
    plan: PlanConfig = Field(default_factory=PlanConfig)
    experiment: ExperimentConfig = Field(default_factory=ExperimentConfig)

    derived: dict[str, str] = Field(
        default_factory=dict, description="settings the library derived, and why "
        "(rrtcolearn.derive; written by the run, informational)")

    @property
    def max_cost(self) -> float:
        """Alg. 2's cost bound, once derived (`rrtcolearn.derive.pilot_max_cost`)."""
        if self.generate.max_cost is None:
            raise ConfigError("generate.max_cost is not derived yet: resolve the "
                              "configuration first (pipeline.resolve)")
        return float(self.generate.max_cost)


# The paper's settings for what the library otherwise derives (rrtcolearn.derive): its
# pendulum experiment exactly, e.g. to reproduce its figures; `paper_config()`.
PAPER: dict[str, dict[str, Any]] = {
    "generate": {"n_simulations": 40_000, "max_cost": 2.0},
    "learn": {"validity_threshold": 0.5, "learner": "knn"},
    "plan": {"sigma": math.pi / 4, "sigma_goal": math.pi / 2, "control_samples": 1,
             "extend_distance": 0.0, "goal_connect": False, "goal_funnel": 0,
             "control_edges": False, "goal_lqr": False, "goal_parent_tries": 0},
}


def paper_config(**sections: dict[str, Any]) -> Config:
    """The paper's pendulum configuration (`PAPER`), with ``sections`` merged over it."""
    data = copy.deepcopy(PAPER)
    _merge(data, copy.deepcopy(sections))
    return validate(data)


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The sections a field's type holds: itself, a list's items, a union's members."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in get_args(annotation) for m in _models(a)]


def _known_keys(model: type[BaseModel], loc: tuple) -> list[str]:
    """The keys of the section an error's location ``loc`` ends in: through lists (an item's
    index) and tagged unions (the obstacle's ``type``, which pydantic puts in the path)."""
    parts = list(loc[:-1])
    while parts:
        field = model.model_fields.get(str(parts.pop(0)))
        members = _models(field.annotation) if field else []
        if parts and isinstance(parts[0], int):  # a list's item
            parts.pop(0)
        if len(members) > 1 and parts:  # a tagged union: the tag names its member
            tag = parts.pop(0)
            members = [m for m in members if "type" in m.model_fields
                       and tag in get_args(m.model_fields["type"].annotation)]
        if len(members) != 1:
            return []
        model = members[0]
    return list(model.model_fields)


def _format_error(exc: ValidationError) -> str:
    errors = exc.errors()
    # a misspelt key is also a missing one: name the misspelling, with its suggestion
    err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    loc = tuple(err["loc"])
    key = ".".join(str(p) for p in loc)
    if err["type"] == "extra_forbidden":
        known = _known_keys(Config, loc)
        typed = str(loc[-1])
        # a key cut short names what it starts (goal_tol: goal_tolerance), else the closest
        close = [k for k in known if k.startswith(typed)][:1] or \
            difflib.get_close_matches(typed, known, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else f" (known keys: {', '.join(known)})"
        return f"config: unknown key {key!r}{hint}"
    msg = err["msg"].removeprefix("Value error, ")
    field, _, rest = msg.partition(": ")
    if isinstance(err.get("input"), dict) and (
            field in err["input"] or field in _known_keys(Config, (*loc, ""))):
        key, msg = f"{key}.{field}", rest  # a section-wide check that names its key
    # the value given, not a whole section's (a section-wide check names its key itself)
    got = f" (got {err['input']!r})" if "input" in err and err["type"] != "missing" and \
        not isinstance(err["input"], dict) else ""
    return f"config: {key}: {msg}{got}"


def validate(data: dict[str, Any]) -> Config:
    """A Config from a nested dict; ConfigError with a one-line message otherwise."""
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_error(exc)) from None


def parse_obstacle(spec: str) -> dict[str, Any]:
    """An ``--obstacle`` spec -> obstacle config: in state space ``box:lo1,..,lon,hi1,..,hin``
    or ``halfplane:n1,..,nn,offset``; in the workspace (for plan.body) ``rect:cx,cy,w,h[,angle]``,
    ``disc:cx,cy,r``, ``polygon:x1,y1,x2,y2,...``, ``sphere:cx,cy,cz,r``."""
    kind, _, values = spec.partition(":")
    try:
        numbers = [float(v) for v in values.split(",")] if values else []
    except ValueError:
        raise ConfigError(f"--obstacle {spec!r}: values must be numbers") from None
    kind = kind.strip().lower()
    if kind == "box":
        if len(numbers) < 2 or len(numbers) % 2:
            raise ConfigError(f"--obstacle {spec!r}: a box needs low and high values, "
                              "e.g. box:-2,-1,-1,1")
        half = len(numbers) // 2
        return {"type": "box", "low": numbers[:half], "high": numbers[half:]}
    if kind == "halfplane":
        if len(numbers) < 2:
            raise ConfigError(f"--obstacle {spec!r}: a half-plane needs a normal and an "
                              "offset, e.g. halfplane:0,1,2.5")
        return {"type": "halfplane", "normal": numbers[:-1], "offset": numbers[-1]}
    shapes = {"rect": (4, 5, "rect:cx,cy,w,h[,angle]"), "disc": (3, 3, "disc:cx,cy,r"),
              "sphere": (4, 4, "sphere:cx,cy,cz,r"), "polygon": (6, 10**6, "polygon:x1,y1,...")}
    if kind in shapes:
        least, most, form = shapes[kind]
        if not least <= len(numbers) <= most or (kind == "polygon" and len(numbers) % 2):
            raise ConfigError(f"--obstacle {spec!r}: give {form}")
        if kind == "rect":
            out = {"shape": "box", "center": numbers[:2], "size": numbers[2:4]}
            return {**out, "angle": numbers[4]} if len(numbers) == 5 else out
        if kind == "polygon":
            return {"shape": "polygon", "vertices": [numbers[i:i + 2]
                                                     for i in range(0, len(numbers), 2)]}
        return {"shape": kind, "center": numbers[:-1], "radius": numbers[-1]}
    raise ConfigError(f"--obstacle {spec!r}: unknown type {kind!r}; use box:... or "
                      "halfplane:... (state space), rect:..., disc:..., polygon:... or "
                      "sphere:... (workspace)")


def add_obstacles(config: Config, specs: list[str]) -> Config:
    """``config`` with the command line's ``--obstacle`` specs appended to plan.obstacles."""
    if not specs:
        return config
    data = config.model_dump()
    data["plan"]["obstacles"] += [parse_obstacle(s) for s in specs]
    return validate(data)


def read_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None


def parse_override(item: str) -> tuple[list[str], Any]:
    """``section.key=value`` -> (["section", "key"], value); the value is read as TOML."""
    if "=" not in item:
        raise ConfigError(f"--set expects section.key=value, got {item!r}")
    key, raw = item.split("=", 1)
    parts = [p.strip() for p in key.strip().split(".")]
    if not all(parts):
        raise ConfigError(f"--set expects section.key=value, got {item!r}")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError as exc:
        if raw[:1] in '[{"\'':  # meant as a list, table or quoted string: malformed
            raise ConfigError(f"--set {item!r}: {raw!r} is not a valid TOML value "
                              f"({exc})") from None
        value = raw  # a bare word is a string
    return parts, value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    for item in overrides:
        parts, value = parse_override(item)
        field = Config.model_fields.get(parts[0]) if len(parts) == 1 else None
        if field is not None and isinstance(field.annotation, type) and \
                issubclass(field.annotation, BaseModel):
            raise ConfigError(f"--set {item!r}: {parts[0]!r} is a section: give "
                              f"{parts[0]}.key=value")
        node = data
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise ConfigError(f"--set {item!r}: {p!r} is not a section")
            node = nxt
        node[parts[-1]] = value
    return data


def load_config(path: str | Path | None = None, overrides: list[str] | None = None,
                base: dict[str, Any] | None = None,
                options: dict[str, Any] | None = None) -> Config:
    """Defaults, then the system's recommended configuration, then ``base``, then the TOML
    file, then ``--set`` overrides, then ``options`` (nested like the file: the command
    line's typed options); validated."""
    data: dict[str, Any] = copy.deepcopy(base or {})
    if path is not None:
        _merge(data, read_toml(path))
    apply_overrides(data, list(overrides or []))
    _merge(data, copy.deepcopy(options or {}))
    return validate(with_system_defaults(data))


def with_system_defaults(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` over the recommended configuration of the system it names (or the default)."""
    from rrtcolearn.systems import recommended_config

    system = data.get("system")
    name = system.get("name", "pendulum") if isinstance(system, dict) else "pendulum"
    merged = copy.deepcopy(recommended_config(name) if isinstance(name, str) else {})
    _merge(merged, data)
    return merged


def _merge(into: dict, new: dict) -> None:
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v


def to_toml(config: Config) -> str:
    return tomli_w.dumps(config.model_dump(exclude_none=True))
