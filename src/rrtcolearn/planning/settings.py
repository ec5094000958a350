"""The planner's settings: one dataclass, its fields grouped by the part of the planner that
reads them (the loop, the learned steering, random controls, the goal connections)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from rrtcolearn import derive
from rrtcolearn.config import Config, GenerateConfig, PlanConfig, SystemConfig
from rrtcolearn.systems.base import System


def _default(section: type, name: str):
    """The configuration's default for ``name`` in ``section``: its one definition."""
    return section.model_fields[name].default


@dataclass(frozen=True)
class PlannerSettings:
    """The planner's settings: the plan section of the configuration (`config.PlanConfig`)
    plus what the planner takes from the data.

    A field that shares its name with a `PlanConfig` field means what that field's
    description says and has its default (one definition, there). None where the
    configuration derives a value is derived here from the problem by the same rules
    (`rrtcolearn.derive`, `resolved`). `from_config` builds the settings from a whole
    configuration. The user-facing configuration keeps its flat ``[plan]`` table; here the
    fields are grouped by the module that reads them.

    time_weight, dt : w of the running cost and the integration step (``system.time_weight``,
        ``generate.dt``).
    max_duration : upper bound of the duration's truncated normal and the longest hold of a
        random control (the data's longest segment; by default ``generate.max_duration``).
    data_reach : the data's longest weighted excursion (``generate.max_state_distance``):
        bounds V's reach (`learned.LearnedSteering.reach`), ``connect_reach`` and the derived
        ``extend_distance``.
    metric_scale : weights of the state coordinates in planner distances (none: the
        system's ``metric_scale``).
    enforce_bounds : edges stop at the state constraints (the bounds OMPL planners are
        given too).
    max_resample : steering draws per candidate when a draw gives no costate.
    funnel_max_cost : the funnel's extremals end at this cost (``generate.max_cost``).
    duration_cap : the configured bound on an extremal's duration (``generate.max_duration``):
        the goal funnel's horizon where the goal has no LQR connection (`rrt.RRTCoLearn`).
    """

    # the problem, the data and the edges' checks (`propagator`)
    time_weight: float = _default(SystemConfig, "time_weight")
    dt: float = _default(GenerateConfig, "dt")
    max_duration: float = _default(GenerateConfig, "max_duration")
    data_reach: float = _default(GenerateConfig, "max_state_distance")
    metric_scale: np.ndarray | None = None
    enforce_bounds: bool = True
    input_limit: str = _default(PlanConfig, "input_limit")
    # the loop (`rrt`)
    goal_bias: float = _default(PlanConfig, "goal_bias")
    stall_iterations: int = _default(PlanConfig, "stall_iterations")
    # the learned steering (`learned`); control_samples also sets the draws of a goal-biased
    # random-control expansion
    sigma: float | None = _default(PlanConfig, "sigma")
    sigma_goal: float | None = _default(PlanConfig, "sigma_goal")
    decimals: int = _default(PlanConfig, "decimals")
    control_samples: int | None = _default(PlanConfig, "control_samples")
    max_candidates: int | None = _default(PlanConfig, "max_candidates")
    extend_distance: float | None = _default(PlanConfig, "extend_distance")
    max_resample: int = 10
    # Newton iterations on the steering parameters that make a learned edge land where it was
    # aimed (`learned.LearnedSteering.refine`); 0 off
    refine_iterations: int = _default(PlanConfig, "refine_iterations")
    parent_cost_to_come: bool = _default(PlanConfig, "parent_cost_to_come")
    # shots at the goal from the cheapest nodes by cost-to-come + J once a solve reached it
    # (`connections.cheaper_goal_edge`); 0 off
    goal_parent_tries: int = _default(PlanConfig, "goal_parent_tries")
    # learned draws dearer than this multiple of J are passed over
    # (`learned.LearnedSteering.propose`); 0 off; "data": from the data
    # (`learned.data_cost_ratio`)
    edge_cost_ratio: float | str = _default(PlanConfig, "edge_cost_ratio")
    # random controls (`controls`; when they switch on: `schedule`)
    control_edges: bool | None = _default(PlanConfig, "control_edges")
    # the goal connections (`connections`; when they switch on: `schedule`); connect_reach
    # also bounds the goal targets the learned steering takes while random controls explore
    goal_connect: bool | None = _default(PlanConfig, "goal_connect")
    connect_reach: float | None = _default(PlanConfig, "connect_reach")
    goal_funnel: int | None = _default(PlanConfig, "goal_funnel")
    funnel_radius: float = _default(PlanConfig, "funnel_radius")
    funnel_duration: float | None = _default(PlanConfig, "funnel_duration")
    funnel_min_duration: float = _default(PlanConfig, "funnel_min_duration")
    funnel_max_cost: float = np.inf
    duration_cap: float = _default(GenerateConfig, "max_duration")
    goal_lqr: bool | None = _default(PlanConfig, "goal_lqr")

    @classmethod
    def from_config(cls, config: Config, **data) -> PlannerSettings:
        """The settings of ``config`` (its plan section, w, dt and cost bound), with
        ``data`` (e.g. ``max_duration``, ``data_reach``) from the fitted model."""
        plan = {f.name: getattr(config.plan, f.name) for f in fields(cls)
                if f.name in PlanConfig.model_fields}
        g = config.generate
        own = {"time_weight": config.system.time_weight, "dt": g.dt,
               "max_duration": g.max_duration, "data_reach": g.max_state_distance,
               "funnel_max_cost": np.inf if g.max_cost is None else g.max_cost,
               "duration_cap": g.max_duration}
        if "plan.funnel_duration" in config.derived and \
                plan["funnel_duration"] == data.get("max_duration"):
            # the value a fit recorded as derived from its data: derived again here, where
            # the problem is known (`rrt.RRTCoLearn`: a goal without an LQR connection)
            plan["funnel_duration"] = None
        return cls(**{**own, **plan, **data})

    def resolved(self, system: System) -> PlannerSettings:
        """Every None that the configuration leaves to the library, derived for ``system``
        (`derive.plan_choices`, the rules the run records in ``config.derived``)."""
        derived = {c.key.split(".")[1]: c.value
                   for c in derive.plan_choices(self, system, self.data_reach)}
        if self.connect_reach is None:
            derived["connect_reach"] = self.data_reach
        if self.funnel_duration is None:
            derived["funnel_duration"] = derive.funnel_duration(self.max_duration).value
        if self.metric_scale is None:
            derived["metric_scale"] = system.metric_scale
        return replace(self, **derived)
