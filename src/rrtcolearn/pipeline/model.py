"""Fitting J, U and V on the cleaned data and loading the fitted model of a run directory:
``model.json`` (parameters and checksums, no pickle) beside ``functions.npz``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rrtcolearn import __version__, derive
from rrtcolearn.config import Config
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.data.store import load_dataset, read_checked_json, write_checked_json
from rrtcolearn.errors import ArtefactError, ConfigError, EnvironmentProblem
from rrtcolearn.learn.features import learning_geometry
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.pipeline.configure import (
    check_dynamics,
    record_choices,
    recorded_system,
    resolve,
    seed_stream,
    system_from_config,
    with_artefact_sections,
)
from rrtcolearn.pipeline.layout import (
    CLEANED_FILE,
    FUNCTIONS_FILE,
    MODEL_FILE,
    existing_run_dir,
    save_config,
)
from rrtcolearn.planning.problem import PlanningProblem
from rrtcolearn.planning.rrt import PlannerSettings, RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems.base import System, dynamics_probe

MODEL_FORMAT = "rrtcolearn.model"
MODEL_SCHEMA = 2


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
            self.config = record_choices(self.config, [derive.Choice(
                "learn.validity_threshold", float(self.functions.validity_.threshold),
                "the fitted classifier's")])
        if learn.learner is None:
            self.config = record_choices(self.config, [derive.Choice(
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
    config = record_choices(config, _learn_choices(system, data, config))
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
    check_dynamics(system, meta.get("dynamics"), str(run_dir / CLEANED_FILE))
    config = with_artefact_sections(config, meta, ("system", "generate", "clean"))
    config = resolve(config, system)
    config = record_choices(config, _learn_choices(system, data, config))
    functions = fit_functions(system, data, config)
    if config.plan.funnel_duration is None:  # from the fitted data, recorded with its reason
        config = record_choices(config, [derive.funnel_duration(functions.max_duration_)])
    save_config(config, run_dir)
    functions_sha = functions.save(run_dir / FUNCTIONS_FILE,
                                   {"system": system.name, "cleaned_sha256": meta["sha256"]})
    write_checked_json(run_dir / MODEL_FILE, {
        "format": MODEL_FORMAT,
        "schema_version": MODEL_SCHEMA,
        "package_version": __version__,
        "system": system.name,
        "dynamics": dynamics_probe(system),
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
    run_dir = existing_run_dir(run_dir)
    info = read_checked_json(run_dir / MODEL_FILE, MODEL_FORMAT, MODEL_SCHEMA, "model file")
    try:
        config = Config.model_validate(info["config"])
    except Exception:
        raise ArtefactError(f"{run_dir / MODEL_FILE} holds an invalid configuration") from None
    config, built = recorded_system(config, info.get("system"), system, f"the model in {run_dir}")
    check_dynamics(built, info.get("dynamics"), f"the model in {run_dir}")
    return info, config, built


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
