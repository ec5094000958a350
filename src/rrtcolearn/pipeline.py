"""The pipeline as library calls: generate -> clean -> fit -> plan, each reading and writing a
run directory. The CLI is a thin layer over these functions.

Run directory layout::

    config.toml     resolved configuration of the last step run here
    dataset.npz     raw data (Alg. 2)
    cleaned.npz     cleaned data (Alg. 3)
    model.json      learner parameters; models are rebuilt from cleaned.npz (no pickle)
    plan.json       the plan of the swing-up query, plan.png its tree (paper Fig. 2)
    summary.json    figures of the last `run`
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn import __version__, derive
from rrtcolearn.config import Config, plan_obstacles, read_toml, to_toml, validate
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.data.store import (
    ShardStore,
    atomic_write_text,
    digest,
    load_arrays,
    load_dataset,
    read_checked_json,
    read_json,
    save_dataset,
    write_checked_json,
    write_json,
)
from rrtcolearn.errors import ArtefactError, ConfigError, EnvironmentProblem
from rrtcolearn.learn.features import learning_geometry
from rrtcolearn.learn.models import FUNCTIONS_FORMAT, LearnedFunctions
from rrtcolearn.planning.problem import PlanningProblem, is_own_limit
from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.planning.tree import Plan
from rrtcolearn.systems import make
from rrtcolearn.systems.base import System

if TYPE_CHECKING:
    from rrtcolearn.data.clean import CleaningResult
    from rrtcolearn.data.generate import GenerationStats
    from rrtcolearn.parallel import ExecutionSettings

# the offline steps (data.generate, data.clean, parallel) are imported by the functions that
# run them: loading a model and planning do without them

DATASET_FILE = "dataset.npz"
CLEANED_FILE = "cleaned.npz"
MODEL_FILE = "model.json"
MODEL_FORMAT = "rrtcolearn.model"
MODEL_SCHEMA = 2
FUNCTIONS_FILE = "functions.npz"

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


def _record(config: Config, choices: list[derive.Choice]) -> Config:
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
    return _record(config, choices)


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


def _meta(config: Config, system: System, **extra) -> dict:
    return {"system": system.name, "config": config.model_dump(mode="json"), **extra}


def read_run_config(run_dir: str | Path) -> Config:
    """The resolved configuration a run directory's last step wrote (``config.toml``)."""
    return validate(read_toml(Path(run_dir) / "config.toml"))


def save_config(config: Config, run_dir: Path) -> None:
    atomic_write_text(Path(run_dir) / "config.toml", to_toml(config))


def _generation_key(config: Config, system: System) -> str:
    """Digest of everything the raw dataset depends on (not of how it is scheduled)."""
    spec = {"seed": config.seed, "system": config.system.model_dump(mode="json"),
            # how n_simulations was chosen does not change the data it gives
            "generate": config.generate.model_dump(mode="json", exclude={"offline_budget"}),
            "goal": _data_goal(config, system),
            "box": [system.state_low.tolist(), system.state_high.tolist(),
                    system.param_low.tolist(), system.param_high.tolist()]}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


def _data_goal(config: Config, system: System) -> list[float] | None:
    """The goal of the backward simulations (the configured query's), if there are any."""
    if not config.generate.goal_simulations:
        return None
    goal = query_states(config, system)[1]
    from rrtcolearn.planning.problem import check_state

    try:
        return check_state(system, goal, "plan.goal").tolist()
    except ValueError as exc:
        raise ConfigError(f"config: {exc}") from None


def generate(config: Config, run_dir: str | Path,
             progress: Callable[[int], None] | None = None,
             settings: ExecutionSettings | None = None) -> tuple[Dataset, GenerationStats]:
    """Alg. 2 with the configured parameters; writes ``dataset.npz``.

    Resumable: each finished chunk is written atomically as a shard under
    ``shards/generate/`` beside a manifest; a rerun with the same configuration loads the
    finished shards and computes only the rest, and a finished dataset is not recomputed.
    """
    from rrtcolearn.data.generate import (
        GenerationStats,
        generation_tasks,
        merge,
        run_generation_task,
    )
    from rrtcolearn.parallel import map_tasks

    run_dir = Path(run_dir)
    system = system_from_config(config)
    config = resolve(config, system)
    if config.generate.n_simulations is None:  # an offline budget: a convergence test
        config = converge_simulations(config, run_dir, system)
    key = _generation_key(config, system)
    final = run_dir / DATASET_FILE
    if final.is_file():
        try:
            data, meta = load_dataset(final, system.name)
            if meta.get("generation_key") == key:
                if meta.get("config", {}).get("derived") != config.derived:
                    # the same data, chosen for reasons the file should carry on
                    save_dataset(final, data, _meta(config, system, stats=meta["stats"],
                                                    generation_key=key))
                save_config(config, run_dir)
                if progress is not None:
                    progress(config.generate.n_simulations)
                # nothing was computed by this call
                return data, dataclasses.replace(GenerationStats(**meta["stats"]),
                                                 worker_cpu_s=0.0)
        except ArtefactError:
            pass  # a damaged or foreign file is regenerated
    g = config.generate
    tasks = generation_tasks(
        system, seed_stream(config.seed, "generate"), g.n_simulations,
        chunk_size=g.chunk_size, **simulation_options(config),
        goal_simulations=g.goal_simulations, goal=_data_goal(config, system))
    shards = ShardStore(run_dir / "shards" / "generate", key, len(tasks))
    parts: list = [shards.load(t.chunk, system.name) for t in tasks]
    todo = [t for t, part in zip(tasks, parts, strict=True) if part is None]
    if progress is not None:
        progress(sum(t.count for t, part in zip(tasks, parts, strict=True) if part is not None))

    computed_cpu = [0.0]

    def finished(i: int, result) -> None:
        task = todo[i]
        computed_cpu[0] += result[1].worker_cpu_s
        shards.save(task.chunk, result, {"system": system.name})
        parts[task.chunk] = result
        if progress is not None:
            progress(task.count)

    map_tasks(run_generation_task, todo, settings, finished)
    data, stats = merge(parts)
    stats = dataclasses.replace(stats, resumed_chunks=len(tasks) - len(todo),
                                worker_cpu_s=computed_cpu[0])
    if g.colearn_rounds:
        data, stats, config = _colearn(config, system, data, stats, run_dir, key)
    save_config(config, run_dir)
    save_dataset(final, data, _meta(config, system, stats=dataclasses.asdict(stats),
                                    generation_key=key))
    _remove_tree(run_dir / "shards" / "colearn")
    shards.remove()  # and shards/ itself, once empty
    return data, stats


def _remove_tree(path: Path) -> None:
    import shutil

    if path.is_dir():
        shutil.rmtree(path)


COLEARN_FILE = "colearn.json"


def _colearn(config: Config, system: System, data: Dataset, stats: GenerationStats,
             run_dir: Path, key: str) -> tuple[Dataset, GenerationStats, Config]:
    """The co-learning rounds (`data.colearn`) after the uniform data: each refit cleans and
    fits as `clean` and `fit` would. Finished rounds are kept under ``shards/colearn`` (keyed
    by the generation key) for a resumed run; the rounds are written to ``colearn.json`` and
    summarised in the config's [derived]."""
    from rrtcolearn.data.colearn import colearn

    g = config.generate
    store = run_dir / "shards" / "colearn" / key[:16]

    def refit(d: Dataset) -> LearnedFunctions:
        return fit_functions(system, clean_dataset(config, system, d)[0], config)

    out, records = colearn(
        system, data, refit, seed=seed_stream(config.seed, "generate"),
        rounds=g.colearn_rounds, simulations=max(1, g.n_simulations // 10),
        first_id=g.n_simulations + g.goal_simulations, store=store,
        **simulation_options(config))
    write_json(run_dir / COLEARN_FILE, [dataclasses.asdict(r) for r in records])
    rates = ", ".join(f"{r.hit_rate:.1%}" for r in records)
    config = _record(config, [derive.Choice(
        "generate.colearn", len(records) - 1,
        f"{len(records) - 1} co-learning round(s); held-out hit rate by round: {rates}")])
    # the loop runs in this process: its CPU is this process's, not the workers'
    stats = dataclasses.replace(
        stats, simulations=stats.simulations + sum(r.simulations for r in records),
        points=len(out))
    return out, stats, config


CONVERGENCE_GAIN = 0.10  # stop doubling the data when the J error improves by less
CONVERGENCE_HELD_OUT = 1000  # held-out pairs of the convergence test


def converge_simulations(config: Config, run_dir: str | Path,
                         system: System | None = None) -> Config:
    """``config`` with ``generate.n_simulations`` chosen by a convergence test within
    ``generate.offline_budget`` CPU seconds: from a quarter of the dimension's default,
    double the simulations, generate, clean and fit k-NN J, and measure its median relative
    error on held-out pairs (simulations from their own seed); stop once doubling improved it
    by less than `CONVERGENCE_GAIN`, or when the next stage (estimated at 2.2 times the last)
    would overrun the budget. The last stage's data stay in ``run_dir`` for `generate`."""
    from rrtcolearn.data.generate import generate_data

    run_dir = Path(run_dir)
    system = system if system is not None else system_from_config(config)
    budget = float(config.generate.offline_budget)
    g = config.generate
    start = derive.n_simulations(system).value // 4
    n = max(g.chunk_size, -(-start // g.chunk_size) * g.chunk_size)
    held, _ = generate_data(system, seed_stream(config.seed, "derive"), 2 * CONVERGENCE_HELD_OUT,
                            **simulation_options(config))
    rows = np.random.default_rng(0).permutation(len(held))[: 20 * CONVERGENCE_HELD_OUT]
    spent, trail, previous = 0.0, [], None
    knn = config.learn.model_copy(update={"learner": "knn"})
    while True:
        t0 = time.process_time()
        stage = config.model_copy(update={"generate": g.model_copy(update={
            "n_simulations": n, "offline_budget": None, "colearn_rounds": 0})})
        _, stats = generate(stage, run_dir)
        cleaned, _ = clean(stage, run_dir)
        functions = fit_functions(system, cleaned, stage.model_copy(update={"learn": knn}))
        cost, _, valid = functions.query(held.inputs[rows])
        truth = held.cost[rows]
        ok = valid & (truth > 0)
        error = float(np.median(np.abs(cost[ok] - truth[ok]) / truth[ok])) if ok.any() \
            else float("inf")
        cpu = time.process_time() - t0 + stats.worker_cpu_s
        spent += cpu
        trail.append(f"{n}: {error:.1%}")
        if previous is not None and error > (1.0 - CONVERGENCE_GAIN) * previous:
            why = "converged: doubling improved held-out J error by less than 10%"
            break
        if spent + 2.2 * cpu > budget:
            why = f"offline budget {budget:g} s CPU: the next doubling would overrun it"
            break
        previous, n = error, 2 * n
    reason = f"{why} (held-out J error by simulations {', '.join(trail)}; {spent:.0f} s CPU)"
    return _record(config, [derive.Choice("generate.n_simulations", n, reason)])


def clean(config: Config, run_dir: str | Path,
          progress: Callable[[int, int], None] | None = None
          ) -> tuple[Dataset, CleaningResult]:
    """Alg. 3 on the run's ``dataset.npz``; writes ``cleaned.npz``."""
    run_dir = Path(run_dir)
    system = system_from_config(config)
    raw, raw_meta = load_dataset(run_dir / DATASET_FILE, system.name)
    cleaned, result = clean_dataset(config, system, raw, progress)
    stats = {"raw_points": len(raw), "kept_points": len(cleaned), "draws": result.draws,
             "dataset_sha256": raw_meta["sha256"]}
    config = _with_sections(config, raw_meta, ("system", "generate"))
    save_config(config, run_dir)
    save_dataset(run_dir / CLEANED_FILE, cleaned, _meta(config, system, stats=stats))
    return cleaned, result


def clean_dataset(config: Config, system: System, raw: Dataset,
                  progress: Callable[[int, int], None] | None = None
                  ) -> tuple[Dataset, CleaningResult]:
    """Alg. 3 with the configured settings on the raw (x0, x1) rows, weighted by the system's
    metric scale.

    Not on the learners' features (`clean_data(features=)`): where coordinates are invariant
    the features fold every start onto one another, and Alg. 3's neighbour search grows
    faster than the data (a first-order unicycle, x and y invariant: 1.6 s on the raw rows
    against 6.2 s on the features at 3 000 simulations, and a 40 000-simulation run was
    stopped after 17 CPU minutes and 16 GB, where the raw rows clean in about 90 s)."""
    from rrtcolearn.data.clean import clean_data

    c = config.clean
    return clean_data(raw, d=c.d, k_max=c.k_max, method=c.method,
                      seed=seed_stream(config.seed, "clean"), progress=progress,
                      scale=system.metric_scale)


def _with_sections(config: Config, meta: dict, sections: tuple[str, ...]) -> Config:
    """``config`` with ``sections`` taken from the artefact it consumes (the truth about it)."""
    stored = meta.get("config", {})
    update = {s: getattr(Config.model_validate(stored), s) for s in sections if s in stored}
    # the reasons of what was derived before travel with the artefact
    update["derived"] = {**stored.get("derived", {}), **config.derived}
    return config.model_copy(update=update)


@dataclass
class FittedModel:
    """Learned J, U, V with what the planner needs to use them."""

    system: System
    config: Config
    functions: LearnedFunctions
    max_duration: float
    max_state_distance: float

    def __post_init__(self) -> None:
        # a model assembled by hand from an unresolved configuration: derive what is open,
        # and take V's threshold from the fitted classifier (the truth about it)
        learn = self.config.learn
        if learn.validity_threshold is None:
            self.config = _record(self.config, [derive.Choice(
                "learn.validity_threshold", float(self.functions.validity_.threshold),
                "the fitted classifier's")])
        if learn.learner is None:
            self.config = _record(self.config, [derive.Choice(
                "learn.learner", self.functions.learner,
                "the fitted learner")])
        self.config = resolve(self.config, self.system)

    def planner_settings(self, config: Config | None = None) -> PlannerSettings:
        """The planner's settings: the plan section of ``config`` (default: the model's
        own) with the model's time weight, step, cost bound and data."""
        own = self.config if config is None else \
            self.config.model_copy(update={"plan": config.plan})
        return PlannerSettings.from_config(own,
                                           max_duration=self.max_duration,
                                           data_reach=self.max_state_distance)


def fit_functions(system: System, data: Dataset, config: Config) -> LearnedFunctions:
    """J, U and V fitted on a (cleaned) dataset with the configured learner (what
    ``config.learn`` leaves open derived first)."""
    config = _record(config, _learn_choices(system, data, config))
    learn = config.learn
    functions = LearnedFunctions(
        n_neighbors=learn.n_neighbors, cost_bounds=(learn.cost_lower, learn.cost_upper),
        validity_threshold=learn.validity_threshold, learner=learn.learner,
        periodic=learn.periodic, mlp_hidden=tuple(learn.mlp_hidden),
        mlp_max_iter=learn.mlp_max_iter, mlp_max_samples=learn.mlp_max_samples,
        seed=int(np.random.SeedSequence(config.seed).generate_state(1)[0] >> 1),
        steering=learn.steering)
    try:
        return functions.fit(data, system)
    except ImportError as exc:
        raise EnvironmentProblem(str(exc)) from None


def _learn_choices(system: System, data: Dataset, config: Config) -> list[derive.Choice]:
    """The learner settings ``config`` leaves open, derived from the system and the data
    (none when all are set), after checking that the data and bounds can be learned from."""
    learn = config.learn
    if learn.cost_lower >= learn.cost_upper:
        raise ConfigError("config: learn.cost_lower must be below learn.cost_upper")
    if len(data) < learn.n_neighbors:
        raise ArtefactError(f"the cleaned dataset has {len(data)} points, fewer than "
                            f"learn.n_neighbors = {learn.n_neighbors}")
    choices = [] if learn.learner is not None else [derive.learner(system)]
    choices.append(derive.invariant_coordinates(system))
    choices.append(derive.planar_rotation(system))
    if learn.validity_threshold is None:
        try:
            features, periodic = learning_geometry(system, learn.periodic)
            choices.append(derive.validity_threshold(
                data.inputs, data.simulation, system.metric_scale, learn.n_neighbors,
                seed_stream(config.seed, "derive"), periodic, features))
        except ValueError as exc:
            raise ArtefactError(str(exc)) from None
    return choices


def fit(config: Config, run_dir: str | Path) -> FittedModel:
    """Fit the learners on ``cleaned.npz``; writes ``model.json`` (parameters, no pickle)."""
    run_dir = Path(run_dir)
    system = system_from_config(config)
    data, meta = load_dataset(run_dir / CLEANED_FILE, system.name)
    config = _with_sections(config, meta, ("system", "generate", "clean"))
    config = resolve(config, system)
    config = _record(config, _learn_choices(system, data, config))
    functions = fit_functions(system, data, config)
    save_config(config, run_dir)
    functions_sha = functions.save(run_dir / FUNCTIONS_FILE,
                                   {"system": system.name, "cleaned_sha256": meta["sha256"]})
    write_checked_json(run_dir / MODEL_FILE, {
        "format": MODEL_FORMAT,
        "schema_version": MODEL_SCHEMA,
        "package_version": __version__,
        "system": system.name,
        "cleaned_file": CLEANED_FILE,
        "cleaned_sha256": meta["sha256"],
        "points": len(data),
        "max_duration": functions.max_duration_,
        "functions_file": FUNCTIONS_FILE,
        "functions_sha256": functions_sha,
        "config": config.model_dump(mode="json"),
    })
    return _fitted_model(system, config, functions)


def _fitted_model(system: System, config: Config, functions: LearnedFunctions
                  ) -> FittedModel:
    """The model of a fit or a load, with the compiled code its plans call loaded
    (compiled the first time, once per system and machine) by a throwaway solve: the first
    plan costs what later ones do."""
    model = FittedModel(system, config, functions, functions.max_duration_,
                        config.generate.max_state_distance)
    _warm_planner(model)
    return model


# iterations of the throwaway solve that loads the planner's own compiled functions
_WARM_ITERATIONS = 50


def _warm_planner(model: FittedModel) -> None:
    """A throwaway solve from the middle of the box toward a goal it cannot reach: it loads
    the system's kernels as every solve does before its clock (`planning.rrt.load_kernels`:
    for an input-limited system also the random-control iterations, and the LQR loop), and
    its iterations load the planner's own compiled functions (the draws' summary, the node
    index's scan), from numba's cache or compiled once per installation (about 2 s),
    instead of inside the first plan's clock. Its outcome does not matter, nor does it
    touch any later plan (its own planner and generator)."""
    system = model.system
    low, high = system.state_low, system.state_high
    try:
        problem = PlanningProblem.create(system, (low + high) / 2, low + 0.75 * (high - low),
                                         1e-9)
        RRTCoLearn(problem, model.functions, model.planner_settings()).solve(
            TerminationCondition(None, _WARM_ITERATIONS), 0)
    except Exception:  # loading is what counts, not the outcome
        pass


def read_model_info(run_dir: str | Path, system: str | None = None
                    ) -> tuple[dict, Config, System]:
    """The checked ``model.json`` of a run directory, its configuration and its system.
    ``system`` (a registered name or module:attribute) rebuilds the system by another name
    than the model records, e.g. a module's function for a name that was registered in
    another Python session; it must build a system of the recorded name."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ArtefactError(f"run directory not found: {run_dir}")
    info = read_checked_json(run_dir / MODEL_FILE, MODEL_FORMAT, MODEL_SCHEMA, "model file")
    try:
        config = Config.model_validate(info["config"])
    except Exception:
        raise ArtefactError(f"{run_dir / MODEL_FILE} holds an invalid configuration") from None
    config, built = recorded_system(config, info.get("system"), system, f"the model in {run_dir}")
    return info, config, built


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


def load_model(run_dir: str | Path, *, model_info: tuple[dict, Config, System] | None = None
               ) -> FittedModel:
    """Rebuild a fitted model from a run directory, checking that its files belong together.

    ``model_info`` is what `read_model_info` returned for this directory, when the caller
    has read it already (the system is then not built twice)."""
    run_dir = Path(run_dir)
    info, config, system = model_info if model_info is not None else read_model_info(run_dir)
    functions, meta = LearnedFunctions.load(run_dir / FUNCTIONS_FILE)
    if meta.get("sha256") != info.get("functions_sha256"):
        raise ArtefactError(f"{run_dir / FUNCTIONS_FILE} is not the file the model was "
                            f"fitted with (checksum differs); rerun `rrtcolearn fit`")
    return _fitted_model(system, config, functions)


_FROM_CONFIG = object()


def query_states(config: Config, system: System) -> tuple[list[float], list[float]]:
    """The configured start and goal, or the system's defaults where they are not set."""
    start = config.plan.start if config.plan.start is not None else \
        system.defaults.get("start")
    goal = config.plan.goal if config.plan.goal is not None else system.defaults.get("goal")
    if start is None or goal is None:
        raise ConfigError(f"system {system.name!r} has no default query: set plan.start and "
                          "plan.goal")
    return list(start), list(goal)


def make_problem(system: System, config: Config, start, goal, goal_tolerance: float, *,
                 u_max=_FROM_CONFIG, obstacles=_FROM_CONFIG, is_valid=None, goal_fn=None,
                 goal_sampler=None) -> PlanningProblem:
    """The query as every planner gets it (`plan` and the experiment's peers alike): the
    configuration's state constraints, goal weights and angle wrapping, its ``u_max`` and
    obstacles unless given, and the system's goal region for its standard goal.

    ``is_valid(states) -> bool array`` adds a user state validity checker; ``goal_fn(states)
    -> distances`` and ``goal_sampler(rng) -> state`` a user goal region (reached where the
    distance is at most ``goal_tolerance``); a system whose ``defaults`` hold them plans to
    that region when ``goal`` is its default goal. A system that saturates its inputs plans
    within its own limits (a different ``u_max`` needs a model trained for it:
    ConfigError); an unbounded one plans under ``u_max`` by truncation (edges whose input
    exceeds it are rejected or cut, plan.input_limit).
    """
    if u_max is _FROM_CONFIG:
        u_max = config.system.u_max
    if system.input_limited:
        low, high = system.input_limits()
        if u_max is not None:
            if not is_own_limit(system, u_max):
                box = ", ".join(f"{lo:g} <= {name} <= {hi:g}" for name, lo, hi in
                                zip(system.input_names, low.tolist(), high.tolist(),
                                    strict=True))
                raise ConfigError(
                    f"u_max {u_max}: the model's inputs saturate at its own limits ({box}), "
                    "which its plans keep: omit u_max, or train a model with the limit you "
                    "want (system.u_max)")
        u_max = None
    elif isinstance(u_max, list):
        raise ConfigError("a model of the unbounded system can plan under a single u_max "
                          "only (by truncation); train a model with the limits instead")
    if obstacles is _FROM_CONFIG:
        obstacles = plan_obstacles(config.plan)
    defaults = system.defaults
    if goal_fn is None and "goal_fn" in defaults and defaults.get("goal") is not None \
            and np.array_equal(np.asarray(goal, dtype=float),
                               np.asarray(defaults["goal"], dtype=float)):
        # the system's standard query comes with its goal region
        goal_fn, goal_sampler = defaults["goal_fn"], defaults.get("goal_sampler")
    p = config.plan
    return PlanningProblem.create(system, start, goal, goal_tolerance, u_max=u_max,
                                  obstacles=obstacles, is_valid=is_valid,
                                  wrap_goal=p.wrap_goal, state_low=p.state_low,
                                  state_high=p.state_high, goal_weights=p.goal_weights,
                                  goal_fn=goal_fn, goal_sampler=goal_sampler)


# ``plan.polish``: each of the round's two improvements within this share of the first
# solve's iterations, in improvement steps (deterministic under a time budget too). On the
# nine problems of bench/ablation.py (5 seeds, bench/polish.py --steps) 0.25 and 1 gave the
# same polished cost on all nine (the improvements end before the allowance); 0.25 cost less
# CPU on sparse_rrt's cart-pole (1.45 s against 2.34 s), where neither gained (docs/anytime.md)
POLISH_ALLOWANCE = 0.25


def _polish_record(result: Plan) -> dict:
    """``plan.polish``'s record for ``extra["polish"]`` (the one-solve anytime record, moved):
    the raw first path's cost and CPU, the polished cost, the CPU of both together, the
    improvement steps spent and whether multiple shooting replaced the path."""
    a = result.extra.pop("anytime")
    return {"first_cost": a["first_solution_cost"], "first_cpu_s": a["first_solution_cpu_s"],
            "cost": float(result.path_cost) if result.solved else None,
            "planning_cpu_s": a["planning_cpu_s"],
            "steps": a["iterations"] - max(1, result.iterations),
            "multiple_shooting": result.extra.get("multiple_shooting", {}).get("kept")}


def plan(model: FittedModel, start, goal, goal_tolerance: float, seed: int = 0, *,
         config: Config | None = None, time_limit: float | None = 10.0,
         max_iterations: int | None = None, u_max=_FROM_CONFIG, obstacles=_FROM_CONFIG,
         is_valid=None, goal_fn=None, goal_sampler=None) -> Plan:
    """Plan one query with a fitted model (Alg. 1): the query `make_problem` makes of the
    arguments (``config`` defaults to the model's), grown into a tree by `RRTCoLearn`; with
    ``plan.anytime`` the whole limit is spent on restarts whose paths are shortcut, inside
    and to the goal (`anytime.solve_with_restarts`, `planning.improve.shortcut`), each new
    best path first by multiple shooting on an allowance of its own
    (`planning.improve.multiple_shooting`); with ``plan.polish`` (and not anytime) the first
    solution gets one such round (`POLISH_ALLOWANCE`), its raw and polished costs in
    ``extra["polish"]``."""
    cfg = config or model.config
    problem = make_problem(model.system, cfg, start, goal, goal_tolerance, u_max=u_max,
                           obstacles=obstacles, is_valid=is_valid, goal_fn=goal_fn,
                           goal_sampler=goal_sampler)
    planner = RRTCoLearn(problem, model.functions, model.planner_settings(config))
    termination = TerminationCondition(time_limit, max_iterations)
    if cfg.plan.anytime or cfg.plan.polish:
        # anytime: the whole budget, restarts, each path shortcut, the cheapest kept;
        # polish: the first solve and its one improvement round only
        from functools import partial

        from rrtcolearn.anytime import solve_with_restarts
        from rrtcolearn.planning.improve import multiple_shooting, shortcut

        polish = not cfg.plan.anytime
        result = solve_with_restarts(planner.solve, termination, seed,
                                     improve=partial(shortcut, planner),
                                     narrowest=planner.narrowest_control_scale(),
                                     first=partial(multiple_shooting, planner),
                                     **({"solves": 1, "allowance": POLISH_ALLOWANCE,
                                         "in_steps": True} if polish else {}))
        if polish:
            result.extra["polish"] = _polish_record(result)
    else:
        result = planner.solve(termination, seed)
    result.extra["seed"] = int(seed) if isinstance(seed, (int, np.integer)) else None
    result.extra["config"] = cfg.model_dump(mode="json")
    return result


PLAN_FORMAT = "rrtcolearn.plan"
PLAN_SCHEMA = 1


def write_plan(p: Plan, path: str | Path) -> None:
    """Write the plan file (JSON, see docs/formats.md) with its checksum."""
    write_checked_json(path, {"format": PLAN_FORMAT, "schema_version": PLAN_SCHEMA,
                              "package_version": __version__, **p.to_dict()})


def _recorded_limits(d: dict) -> dict:
    """The system section's input limits of a plan that saturated its inputs, from the box
    the plan file records (a plan without its configuration)."""
    low, high = d.get("input_low"), d.get("input_high")
    if d.get("limit_mode") != "saturate" or not isinstance(low, list) or \
            not isinstance(high, list) or None in low or None in high:
        return {}
    if all(lo == -hi for lo, hi in zip(low, high, strict=False)):
        return {"u_max": high[0] if len(high) == 1 else high}
    return {"u_low": low, "u_high": high}


def plan_system(d: dict, system: str | None = None) -> System:
    """The system a plan file's content (`read_plan`) was planned on, rebuilt from the
    configuration the plan records (a registered name or module:attribute, its limits), or
    by ``system`` (`recorded_system`)."""
    if not isinstance(d.get("config"), dict):
        # a plan of the Planner API written as it is: only its system's name is recorded
        if system is None:
            raise ConfigError("the plan file records no configuration: it cannot say which "
                              "system to re-simulate it on (give it: --system NAME or "
                              "module:attribute)")
        d = {**d, "config": {"system": {"name": system, **_recorded_limits(d)}}}
    _, system = recorded_system(validate(d["config"]), d.get("system"), system, "the plan")
    if system.name != d.get("system"):
        raise ConfigError(f"the plan is for system {d.get('system')!r}, its configuration "
                          f"builds {system.name!r}")
    return system


def read_plan(path: str | Path) -> dict:
    """A checked plan file."""
    return read_checked_json(path, PLAN_FORMAT, PLAN_SCHEMA, "plan file")


def timed(fn, *args, **kwargs):
    """(result, CPU seconds of this process). Worker processes are kept between calls, so
    their CPU is reported by the work itself (``GenerationStats.worker_cpu_s``)."""
    t0 = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - t0


_TIMING_KEYS = {"planning_time_s", "planning_cpu_s", "wall_s", "generate_cpu_s", "clean_cpu_s",
                "fit_cpu_s", "offline_cpu_s"}


def content_digest(path: str | Path) -> tuple[str, str]:
    """(kind, SHA-256) of an artefact's content, independent of chunking and file layout.

    Datasets: the expanded arrays (x0, x1, cost, params, duration, costate, simulation) in
    name order; fitted functions: their arrays; JSON and TOML: the canonical JSON of their
    content without timing fields; anything else: the file's bytes.
    """
    path = Path(path)
    if path.name == FUNCTIONS_FILE:
        arrays, _ = load_arrays(path, FUNCTIONS_FORMAT)
        return "functions", digest(arrays)
    if path.suffix == ".npz":
        data, _ = load_dataset(path)
        return "dataset", digest(data.arrays())
    if path.suffix in (".json", ".toml"):
        content = read_json(path) if path.suffix == ".json" else read_toml(path)
        if isinstance(content, dict):
            content = {k: v for k, v in content.items() if k not in _TIMING_KEYS}
        canon = json.dumps(content, sort_keys=True, separators=(",", ":"))
        return path.suffix[1:], hashlib.sha256(canon.encode()).hexdigest()
    return "file", hashlib.sha256(path.read_bytes()).hexdigest()


def inspect_run(run_dir: str | Path) -> list[dict]:
    """Size and content digest of every artefact in a run directory."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ArtefactError(f"run directory not found: {run_dir}")
    rows = []
    for path in sorted(p for p in run_dir.iterdir() if p.is_file()
                       and not p.name.startswith(".")):
        kind, sha = content_digest(path)
        rows.append({"file": path.name, "kind": kind, "bytes": path.stat().st_size,
                     "sha256": sha})
    return rows
