"""The pipeline as library calls: generate -> clean -> fit -> plan, each reading and writing a
run directory (its layout: `rrtcolearn.pipeline.layout`). The CLI is a thin layer over these
functions; every public name is re-exported here, so ``from rrtcolearn import pipeline`` and
``pipeline.plan(...)`` is how the library is used.

Modules, by job (each imports only modules above it in this list):

    configure   the run's configuration resolved: seed streams, the configured system,
                derived settings (`resolve`), the configured query, a recorded system
    layout      the run directory's file names and its config.toml
    model       fit J, U, V (`fit`, `fit_functions`), `FittedModel`, `load_model`
    offline     Alg. 2 (`generate`: convergence test, co-learning) and Alg. 3 (`clean`)
    plans       the query (`make_problem`), `plan`, the plan file
    inspection  a step's CPU time (`timed`), the artefacts' digests (`inspect_run`)
"""

from rrtcolearn.pipeline.configure import (
    query_states,
    recorded_system,
    resolve,
    seed_stream,
    simulation_options,
    system_from_config,
)
from rrtcolearn.pipeline.inspection import content_digest, inspect_run, timed
from rrtcolearn.pipeline.layout import (
    CLEANED_FILE,
    COLEARN_FILE,
    DATASET_FILE,
    FUNCTIONS_FILE,
    MODEL_FILE,
    read_run_config,
    save_config,
)
from rrtcolearn.pipeline.model import (
    MODEL_FORMAT,
    MODEL_SCHEMA,
    FittedModel,
    fit,
    fit_functions,
    load_model,
    read_model_info,
)
from rrtcolearn.pipeline.offline import (
    CONVERGENCE_GAIN,
    CONVERGENCE_HELD_OUT,
    clean,
    clean_dataset,
    converge_simulations,
    generate,
)
from rrtcolearn.pipeline.plans import (
    PLAN_FORMAT,
    PLAN_SCHEMA,
    POLISH_ALLOWANCE,
    make_problem,
    plan,
    plan_system,
    read_plan,
    write_plan,
)

__all__ = [
    "CLEANED_FILE", "COLEARN_FILE", "CONVERGENCE_GAIN", "CONVERGENCE_HELD_OUT",
    "DATASET_FILE", "FUNCTIONS_FILE", "MODEL_FILE", "MODEL_FORMAT", "MODEL_SCHEMA",
    "PLAN_FORMAT", "PLAN_SCHEMA", "POLISH_ALLOWANCE", "FittedModel", "clean", "clean_dataset",
    "content_digest", "converge_simulations", "fit", "fit_functions", "generate",
    "inspect_run", "load_model", "make_problem", "plan", "plan_system", "query_states",
    "read_model_info", "read_plan", "read_run_config", "recorded_system",
    "resolve", "save_config", "seed_stream", "simulation_options", "system_from_config",
    "timed", "write_plan",
]
