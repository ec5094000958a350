"""The run's configuration resolved: its random streams, the configured system, the settings
the library derives (`resolve`), the configured query, and the system a model or plan file
records. Every other step of the pipeline starts here."""

from __future__ import annotations

import dataclasses

import numpy as np

from rrtcolearn import derive
from rrtcolearn.config import Config
from rrtcolearn.errors import ArtefactError, ConfigError
from rrtcolearn.systems import make
from rrtcolearn.systems.base import System, dynamics_mismatch

_STREAMS = {"generate": 0, "clean": 1, "plan": 2, "derive": 3}


def seed_stream(seed: int, step: str) -> np.random.SeedSequence:
    """Independent random stream of one pipeline step, derived from the run's seed."""
    return np.random.SeedSequence(seed, spawn_key=(_STREAMS[step],))


def system_from_config(config: Config) -> System:
    """The configured system, with any sampling-box overrides applied and checked."""
    try:
        system = make(config.system.name)
    except ValueError as exc:
        raise ConfigError(f"config: system.name: {exc}") from None
    # the limits first: a shipped system with configured limits comes from its own build
    # record, and the overrides below are fields that `with_input_limits` keeps
    system = _with_configured_limits(config, system)
    g = config.generate
    changes = {}
    for key, n in (("state_low", system.n_states), ("state_high", system.n_states),
                   ("param_low", system.n_params), ("param_high", system.n_params)):
        value = getattr(g, key)
        if value is not None:
            if len(value) != n:
                raise ConfigError(f"config: generate.{key} needs {n} values, got {len(value)}")
            changes[key] = np.asarray(value, dtype=np.float64)
    scale = config.system.input_scale
    if scale is not None:
        if len(scale) != system.n_states or not all(v > 0 for v in scale):
            raise ConfigError(f"config: system.input_scale needs {system.n_states} positive "
                              f"values, got {scale}")
        changes["input_scale"] = np.asarray(scale, dtype=np.float64)
    system = dataclasses.replace(system, **changes)
    if np.any(system.state_low >= system.state_high):
        raise ConfigError("config: generate.state_low must be below state_high")
    if np.any(system.param_low >= system.param_high):
        raise ConfigError("config: generate.param_low must be below param_high")
    return system


def record_choices(config: Config, choices: list[derive.Choice]) -> Config:
    """``config`` with each choice's value set and its reason in ``config.derived``; a
    choice that is no setting of its section (what the system shows, e.g. its invariant
    coordinates) is recorded in ``config.derived`` only."""
    if not choices:
        return config
    data = config.model_dump()
    for c in choices:
        section, key = c.key.split(".")
        if key in type(getattr(config, section)).model_fields:
            data[section][key] = c.value
        data["derived"][c.key] = c.text
    return Config.model_validate(data)


def resolve(config: Config, system: System | None = None) -> Config:
    """``config`` with every setting left to the library (None) derived from the system
    (`rrtcolearn.derive`): Alg. 2's simulations and cost bound, the learner, and the
    planner's steering noise, control samples and target extension. The validity threshold
    needs the data and is derived by `fit`. Settings the user gave are kept."""
    system = system if system is not None else system_from_config(config)
    g = config.generate
    choices = []
    if g.n_simulations is None and g.offline_budget is None:
        choices.append(derive.n_simulations(system))
    if g.max_cost is None:
        choices.append(derive.pilot_max_cost(
            system, time_weight=config.system.time_weight, dt=g.dt,
            max_state_distance=g.max_state_distance, max_duration=g.max_duration,
            seed=seed_stream(config.seed, "derive"), u_max=config.system.truncation_limit))
    if config.learn.learner is None:
        choices.append(derive.learner(system))
    choices += derive.plan_choices(config.plan, system, g.max_state_distance)
    return record_choices(config, choices)


def replaced_limits(config: Config) -> derive.Choice | None:
    """A record (shown with the derived settings) that the configured input limits replace
    other ones the system's definition declares, which is documented but was silent: a
    definition with |tau| <= 0.6 fitted with ``--u-max 1`` plans with |u| up to 1. None
    when the configuration sets no limits or the definition declares none or the same.
    Made where the data are (`offline.generate`: the definition is built again here) and
    carried by every file made from them, not at every load."""
    bounds = config.system.input_bounds()
    if bounds is None or config.system.limit_mode == "truncate":
        return None
    own = make(config.system.name)  # as the definition declares it
    if not own.input_limited:
        return None
    low, high = own.input_limits()
    if np.array_equal(low, bounds[0]) and np.array_equal(high, bounds[1]):
        return None

    def box(lo, hi) -> str:
        return ", ".join(f"{a:g} <= {name} <= {b:g}"
                         for name, a, b in zip(own.input_names, lo, hi, strict=True))

    return derive.Choice("system.input_limits", box(*bounds),
                         f"configured: they replace the limits the system's definition "
                         f"declares ({box(low, high)})")


def simulation_options(config: Config) -> dict:
    """The options of Alg. 2's simulations (`data.generate.generate_data`,
    `generation_tasks`, `simulate_from`) in a resolved ``config``: w, dt, the cost bound, the
    reach, the truncation limit and the longest duration, named as those functions take them."""
    g = config.generate
    return {"time_weight": config.system.time_weight, "dt": g.dt, "max_cost": config.max_cost,
            "max_state_distance": g.max_state_distance,
            "u_max": config.system.truncation_limit, "max_duration": g.max_duration}


def _with_configured_limits(config: Config, system: System) -> System:
    """``system`` with the configured input limits: saturated optimal control over the input
    box, or (limit_mode 'truncate') the unconstrained system whose extremals are cut at u_max.
    Without configured limits the system keeps its own."""
    sc = config.system
    bounds = sc.input_bounds()
    if sc.limit_mode == "truncate":
        bounds = (None, None) if system.input_limited else None
    if bounds is None:
        return system
    from rrtcolearn.systems.generated import SymbolicSystem

    try:
        if isinstance(system, SymbolicSystem) and system.definition is not None:
            # a shipped system: the limited one has a build record of its own (no sympy)
            from rrtcolearn.systems.build_record import build

            return build(system.definition, bounds)
        from rrtcolearn.systems.symbolic import with_input_limits

        return with_input_limits(system, *bounds)
    except ValueError as exc:
        raise ConfigError(f"config: system input limits: {exc}") from None


def with_artefact_sections(config: Config, meta: dict, sections: tuple[str, ...]) -> Config:
    """``config`` with ``sections`` taken from the artefact it consumes (the truth about it)."""
    stored = meta.get("config", {})
    update = {s: getattr(Config.model_validate(stored), s) for s in sections if s in stored}
    # the reasons of what was derived before travel with the artefact
    update["derived"] = {**stored.get("derived", {}), **config.derived}
    return config.model_copy(update=update)


def recorded_system(config: Config, recorded: str | None, system: str | None, what: str
                    ) -> tuple[Config, System]:
    """The system a model or plan file records (``recorded``: its `System.name`, under
    ``config.system.name``), and the configuration it is built from. ``system`` (a
    registered name or module:attribute) builds it by another name, which the returned
    configuration then carries; it must build a system named ``recorded``. A name that
    only another Python session registered is a ConfigError that says how to name it."""
    from rrtcolearn.systems import list_systems

    if system is not None and system != config.system.name:
        try:
            other = make(system)
        except ValueError as exc:
            raise ConfigError(f"--system: {exc}") from None
        if recorded is not None and other.name != recorded:
            raise ConfigError(f"--system {system} builds system {other.name!r}; {what} is "
                              f"for {recorded!r}")
        config = config.model_copy(update={
            "system": config.system.model_copy(update={"name": system})})
    name = config.system.name
    if ":" not in name and name not in list_systems():
        raise ConfigError(
            f"{what} is for system {name!r}, which is not registered in this process (a name "
            "given to `register` lasts only for the Python session that registered it): "
            "register it before loading, or on the command line give --system "
            "module:attribute naming the function that builds it")
    return config, system_from_config(config)


def check_dynamics(system: System, recorded: object, what: str) -> None:
    """An ArtefactError unless ``recorded`` (the `dynamics_probe` a dataset or model file
    holds) is ``system``'s dynamics and running cost: a definition edited after the fit
    keeps its name, and its model would plan with dynamics it never learned. Files written
    before the record (``recorded`` None) are not checked."""
    if recorded is None:
        return
    why = dynamics_mismatch(system, recorded)
    if why is not None:
        raise ArtefactError(f"{what} was made for other dynamics than system {system.name!r} "
                            f"has now ({why}): give the system it was made with, or make it "
                            "again for this one (`rrtcolearn run`)")


def query_states(config: Config, system: System) -> tuple[list[float], list[float]]:
    """The configured start and goal, or the system's defaults where they are not set."""
    start = config.plan.start if config.plan.start is not None else \
        system.defaults.get("start")
    goal = config.plan.goal if config.plan.goal is not None else system.defaults.get("goal")
    if start is None or goal is None:
        raise ConfigError(f"system {system.name!r} has no default query: set plan.start and "
                          "plan.goal")
    return list(start), list(goal)
