"""The offline steps over a run directory: Alg. 2's data (`generate`, resumable, with the
convergence test of an offline budget and the co-learning rounds) and Alg. 3's cleaning
(`clean`)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rrtcolearn import derive
from rrtcolearn.config import Config
from rrtcolearn.data.dataset import Dataset
from rrtcolearn.data.store import ShardStore, load_dataset, save_dataset, write_json
from rrtcolearn.errors import ArtefactError, ConfigError
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.pipeline.configure import (
    check_dynamics,
    query_states,
    record_choices,
    replaced_limits,
    resolve,
    seed_stream,
    simulation_options,
    system_from_config,
    with_artefact_sections,
)
from rrtcolearn.pipeline.layout import CLEANED_FILE, COLEARN_FILE, DATASET_FILE, save_config
from rrtcolearn.pipeline.model import fit_functions
from rrtcolearn.systems.base import System, dynamics_probe

if TYPE_CHECKING:
    from rrtcolearn.data.clean import CleaningResult
    from rrtcolearn.data.generate import GenerationStats
    from rrtcolearn.parallel import ExecutionSettings

# the offline steps (data.generate, data.clean, parallel) are imported by the functions that
# run them: loading a model and planning do without them


def _meta(config: Config, system: System, **extra) -> dict:
    return {"system": system.name, "dynamics": dynamics_probe(system),
            "config": config.model_dump(mode="json"), **extra}


def _generation_key(config: Config, system: System) -> str:
    """Digest of everything the raw dataset depends on (not of how it is scheduled)."""
    spec = {"seed": config.seed, "system": config.system.model_dump(mode="json"),
            # how n_simulations was chosen does not change the data it gives
            "generate": config.generate.model_dump(mode="json", exclude={"offline_budget"}),
            "goal": _data_goal(config, system),
            # the dynamics themselves: a definition edited under the same name
            "dynamics": dynamics_probe(system),
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
    replaced = replaced_limits(config)
    if replaced is not None:
        config = record_choices(config, [replaced])
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
    config = record_choices(config, [derive.Choice(
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
    return record_choices(config, [derive.Choice("generate.n_simulations", n, reason)])


def clean(config: Config, run_dir: str | Path,
          progress: Callable[[int, int], None] | None = None
          ) -> tuple[Dataset, CleaningResult]:
    """Alg. 3 on the run's ``dataset.npz``; writes ``cleaned.npz``."""
    run_dir = Path(run_dir)
    system = system_from_config(config)
    raw, raw_meta = load_dataset(run_dir / DATASET_FILE, system.name)
    check_dynamics(system, raw_meta.get("dynamics"), str(run_dir / DATASET_FILE))
    cleaned, result = clean_dataset(config, system, raw, progress)
    stats = {"raw_points": len(raw), "kept_points": len(cleaned), "draws": result.draws,
             "dataset_sha256": raw_meta["sha256"]}
    config = with_artefact_sections(config, raw_meta, ("system", "generate"))
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
