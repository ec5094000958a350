"""Alg. 2 (generate_data): sample start states, costates on H* = 0 and integrate.

Every intermediate RK4 step of a simulation is a data point (paper Section 3), and a
simulation stops when its cost exceeds ``max_cost`` or its state leaves the ball of radius
``max_state_distance`` around its start (paper Experiments: 2 and 1.5).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.integrate import rollout_batch
from rrtcolearn.parallel import ExecutionSettings, map_tasks
from rrtcolearn.systems.base import System


@dataclass(frozen=True)
class GenerationStats:
    simulations: int
    invalid_costates: int
    empty_simulations: int
    points: int
    nonfinite_simulations: int = 0  # stopped by overflow or NaN; their finite prefix is kept
    resumed_chunks: int = 0  # chunks loaded from shards of an interrupted run
    worker_cpu_s: float = 0.0  # CPU time of the simulations computed (not resumed) by this call,
    # in whichever process ran them


def sample_starts(system: System, seed: int | np.random.SeedSequence, first: int, n: int,
                  w: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Start states, costate parameters and costates of simulations first..first+n-1.

    Simulation i takes its uniforms from block i of one counter-based (Philox) stream keyed
    by ``seed``, so its start never depends on how simulations are split into chunks.
    Returns (x0, p, lam, valid).
    """
    ns = system.n_states
    u = _uniforms(system, seed, first, n)
    x0 = system.state_low + (system.state_high - system.state_low) * u[:, :ns]
    p = system.param_low + (system.param_high - system.param_low) * u[:, ns : ns + system.n_params]
    lam, valid = system.costate_from_params(x0, p, w)
    return x0, p, lam, valid


def _uniforms(system: System, seed: int | np.random.SeedSequence, first: int, n: int
              ) -> np.ndarray:
    """Uniforms (n, >= n_states + n_params) of simulations first..first+n-1 (block i of a
    Philox stream for simulation i)."""
    stride = 4 * -(-(system.n_states + system.n_params) // 4)  # 4 doubles per counter step
    bitgen = np.random.Philox(_fresh(seed))
    bitgen.advance(first * stride // 4)
    return np.random.Generator(bitgen).random((n, stride))


def simulate_chunk(
    system: System,
    seed: np.random.SeedSequence | int,
    n_simulations: int,
    first_index: int,
    *,
    time_weight: float,
    dt: float,
    max_cost: float,
    max_state_distance: float,
    u_max: float | None = None,
    max_duration: float = 20.0,
) -> tuple[Dataset, GenerationStats]:
    """Generate the data points of ``n_simulations`` simulations from one seed."""
    cpu0 = time.process_time()
    x0, p, lam, valid = sample_starts(system, seed, first_index, n_simulations, time_weight)
    sim_index = first_index + np.flatnonzero(valid)
    chunk, stats = simulate_from(
        system, x0[valid], p[valid], lam[valid], sim_index, time_weight=time_weight, dt=dt,
        max_cost=max_cost, max_state_distance=max_state_distance, u_max=u_max,
        max_duration=max_duration)
    return chunk, dataclasses.replace(
        stats, simulations=n_simulations, invalid_costates=int(n_simulations - valid.sum()),
        worker_cpu_s=time.process_time() - cpu0)


def simulate_from(system: System, x0: np.ndarray, p: np.ndarray, lam: np.ndarray,
                  sim_index: np.ndarray, *, time_weight: float, dt: float, max_cost: float,
                  max_state_distance: float, u_max: float | None = None,
                  max_duration: float = 20.0) -> tuple[CompactChunk, GenerationStats]:
    """Alg. 2's simulations from given starts ``x0`` (S, n) with costates ``lam`` on H* = 0
    (parameters ``p``), numbered ``sim_index``: every RK4 step is a data point. Uniform
    generation and the co-learning loop's aimed simulations (`data.colearn`) share it."""
    cpu0 = time.process_time()
    n = system.n_states
    z0 = np.hstack([x0, lam, np.zeros((len(x0), 1))])
    # cost >= w*t bounds every simulation's duration; max_duration caps it regardless
    max_steps = int(min(np.ceil(max_cost / (time_weight * dt)) + 1, np.ceil(max_duration / dt)))
    states, costs, lengths, nonfinite = rollout_batch(
        system, z0, time_weight, dt, max_steps, max_cost, max_state_distance, n, u_max=u_max,
    )
    mask = np.arange(max_steps)[None, :] < lengths[:, None]
    rows, steps = np.nonzero(mask)
    chunk = CompactChunk(x0=x0, params=p, costate=lam,
                         simulation=np.asarray(sim_index).astype(np.int64),
                         point_sim=rows.astype(np.int32), x1=states[rows, steps],
                         cost=costs[rows, steps], step=(steps + 1).astype(np.int32), dt=dt)
    stats = GenerationStats(
        simulations=len(x0), invalid_costates=0,
        empty_simulations=int((lengths == 0).sum()), points=len(rows),
        nonfinite_simulations=int(nonfinite.sum()), worker_cpu_s=time.process_time() - cpu0)
    return chunk, stats


def simulate_goal_chunk(
    system: System,
    seed: np.random.SeedSequence | int,
    n_simulations: int,
    first_index: int,
    goal: np.ndarray,
    *,
    time_weight: float,
    dt: float,
    max_cost: float,
    max_state_distance: float,
    u_max: float | None = None,
    max_duration: float = 20.0,
    id_offset: int = 0,
) -> tuple[Dataset, GenerationStats]:
    """Data points that end at ``goal``: simulations integrated backwards in time from it.

    Each simulation starts at the goal with a costate on H* = 0 (parameters drawn as in
    `sample_starts`) and runs backwards; every state x(-t) it passes is the start of an
    optimal segment of duration t that ends at the goal, with the costate found there, so
    the pair (x(-t), goal) is a data point like any other (its stored costate is the one its
    parameters give, which differs from the integrated one by RK4's error). In higher
    dimensions the planner's last connection needs such pairs, which forward simulations
    from sampled starts almost never provide. Simulation ids are ``id_offset + index``.
    """
    cpu0 = time.process_time()
    if system.params_from_costate is None:
        raise ValueError(f"system {system.name!r} has no params_from_costate: it cannot use "
                         "goal simulations")
    n, k = system.n_states, system.n_params
    u = _uniforms(system, seed, first_index, n_simulations)
    p = system.param_low + (system.param_high - system.param_low) * u[:, n : n + k]
    xg = np.repeat(np.asarray(goal, dtype=np.float64)[None], n_simulations, axis=0)
    lam, valid = system.costate_from_params(xg, p, time_weight)
    sim_index = id_offset + first_index + np.flatnonzero(valid)
    z0 = np.hstack([xg[valid], lam[valid], np.zeros((int(valid.sum()), 1))])
    max_steps = int(min(np.ceil(max_cost / (time_weight * dt)) + 1, np.ceil(max_duration / dt)))
    states, costs, lengths, nonfinite = rollout_batch(
        system, z0, time_weight, -dt, max_steps, max_cost, max_state_distance, n, u_max=u_max,
        with_costate=True)
    rows, steps = np.nonzero(np.arange(max_steps)[None, :] < lengths[:, None])
    x0, lam0 = states[rows, steps, :n], states[rows, steps, n:]
    params = system.params_from_costate(x0, lam0)
    shift = system.wrap_shift(x0)  # angles into the box; the goal shifts with them
    x0 = x0 + shift
    x1 = xg[0] + shift
    # RK4 keeps H* = 0 only to ~1e-7 over a segment: store the costate that the parameters
    # give (exactly on the surface), which is the one a planner steers with
    ok = np.isfinite(params).all(axis=1)
    lam_p = np.full_like(lam0, np.nan)
    lam_p[ok], valid_p = system.costate_from_params(x0[ok], params[ok], time_weight)
    ok[ok] = valid_p
    b = system.bounded_dims
    keep = ok & np.all(
        (x0[:, b] >= system.state_low[b]) & (x0[:, b] <= system.state_high[b]), axis=1)
    data = Dataset(x0=x0[keep], x1=x1[keep], cost=-costs[rows, steps][keep],
                   params=params[keep], duration=((steps + 1) * dt)[keep],
                   costate=lam_p[keep], simulation=sim_index[rows][keep].astype(np.int64))
    stats = GenerationStats(
        simulations=n_simulations, invalid_costates=int(n_simulations - valid.sum()),
        empty_simulations=int((lengths == 0).sum()), points=len(data),
        nonfinite_simulations=int(nonfinite.sum()), worker_cpu_s=time.process_time() - cpu0)
    return data, stats


@dataclass
class CompactChunk:
    """A chunk's rows without repeating per-simulation values: what workers send back.

    Per simulation: x0, params, costate, simulation index; per point: the simulation it
    belongs to (local index), x1, cost and step count. ``expand`` gives the `Dataset`.
    """

    x0: np.ndarray
    params: np.ndarray
    costate: np.ndarray
    simulation: np.ndarray
    point_sim: np.ndarray
    x1: np.ndarray
    cost: np.ndarray
    step: np.ndarray
    dt: float

    def expand(self) -> Dataset:
        s = self.point_sim
        return Dataset(x0=np.take(self.x0, s, axis=0), x1=self.x1, cost=self.cost,
                       params=np.take(self.params, s, axis=0), duration=self.step * self.dt,
                       costate=np.take(self.costate, s, axis=0),
                       simulation=np.take(self.simulation, s))

    @classmethod
    def concatenate(cls, parts: list[CompactChunk]) -> CompactChunk:
        offsets = np.cumsum([0] + [len(c.simulation) for c in parts[:-1]])
        return cls(
            x0=np.concatenate([c.x0 for c in parts]),
            params=np.concatenate([c.params for c in parts]),
            costate=np.concatenate([c.costate for c in parts]),
            simulation=np.concatenate([c.simulation for c in parts]),
            point_sim=np.concatenate([c.point_sim.astype(np.int64) + o
                                      for c, o in zip(parts, offsets, strict=True)]),
            x1=np.concatenate([c.x1 for c in parts]),
            cost=np.concatenate([c.cost for c in parts]),
            step=np.concatenate([c.step for c in parts]),
            dt=parts[0].dt,
        )


def _fresh(seed: int | np.random.SeedSequence) -> np.random.SeedSequence:
    """A SeedSequence that has spawned nothing yet, so spawning is reproducible."""
    if isinstance(seed, np.random.SeedSequence):
        return np.random.SeedSequence(seed.entropy, spawn_key=seed.spawn_key)
    return np.random.SeedSequence(seed)


def concatenate(parts: list[Dataset]) -> Dataset:
    """Rows of several datasets, in order."""
    arrays = [p.arrays() for p in parts]
    return Dataset.from_arrays({k: np.concatenate([a[k] for a in arrays]) for k in arrays[0]})


@dataclass(frozen=True)
class GenerationTask:
    """One chunk of Alg. 2: picklable, carrying its own seed."""

    system: System
    chunk: int
    first: int
    count: int
    seed: np.random.SeedSequence
    time_weight: float
    dt: float
    max_cost: float
    max_state_distance: float
    u_max: float | None
    max_duration: float = 20.0
    goal: tuple[float, ...] | None = None  # backward simulations from this goal
    id_offset: int = 0


def run_generation_task(task: GenerationTask) -> tuple[Dataset, GenerationStats]:
    """Generate one chunk (top-level so that worker processes can import it)."""
    if task.goal is not None:
        return simulate_goal_chunk(
            task.system, task.seed, task.count, task.first, np.asarray(task.goal),
            time_weight=task.time_weight, dt=task.dt, max_cost=task.max_cost,
            max_state_distance=task.max_state_distance, u_max=task.u_max,
            max_duration=task.max_duration, id_offset=task.id_offset)
    return simulate_chunk(
        task.system, task.seed, task.count, task.first, time_weight=task.time_weight,
        dt=task.dt, max_cost=task.max_cost, max_state_distance=task.max_state_distance,
        u_max=task.u_max, max_duration=task.max_duration)


def generation_tasks(
    system: System,
    seed: int | np.random.SeedSequence,
    n_simulations: int,
    *,
    time_weight: float = 1.0,
    dt: float = 0.01,
    max_cost: float = 2.0,
    max_state_distance: float = 1.5,
    chunk_size: int = 2000,
    u_max: float | None = None,
    max_duration: float = 20.0,
    goal_simulations: int = 0,
    goal: np.ndarray | None = None,
) -> list[GenerationTask]:
    """Alg. 2 split into chunks of ``chunk_size`` simulations (see `sample_starts`), then
    ``goal_simulations`` backward simulations from ``goal`` (see `simulate_goal_chunk`)
    from their own random stream."""
    if n_simulations < 1 or chunk_size < 1 or goal_simulations < 0:
        raise ValueError("n_simulations and chunk_size must be positive")
    n_chunks = -(-n_simulations // chunk_size)
    root = _fresh(seed)
    tasks = [
        GenerationTask(system, c, c * chunk_size,
                       min(chunk_size, n_simulations - c * chunk_size), root, time_weight, dt,
                       max_cost, max_state_distance, u_max, max_duration)
        for c in range(n_chunks)
    ]
    if goal_simulations:
        if goal is None:
            raise ValueError("goal simulations need a goal")
        goal_root = np.random.SeedSequence(root.entropy, spawn_key=(*root.spawn_key, 1))
        goal_t = tuple(float(v) for v in np.asarray(goal, dtype=np.float64))
        for c in range(-(-goal_simulations // chunk_size)):
            tasks.append(GenerationTask(
                system, len(tasks), c * chunk_size,
                min(chunk_size, goal_simulations - c * chunk_size), goal_root, time_weight,
                dt, max_cost, max_state_distance, u_max, max_duration, goal_t,
                id_offset=n_simulations))
    return tasks


def merge(parts: list[tuple[CompactChunk | Dataset, GenerationStats]]
          ) -> tuple[Dataset, GenerationStats]:
    """Chunks in chunk order -> one dataset and summed statistics."""
    stats = [st for _, st in parts]
    chunks = [c for c, _ in parts]
    total = GenerationStats(
        simulations=sum(s.simulations for s in stats),
        invalid_costates=sum(s.invalid_costates for s in stats),
        empty_simulations=sum(s.empty_simulations for s in stats),
        points=sum(s.points for s in stats),
        nonfinite_simulations=sum(s.nonfinite_simulations for s in stats),
        worker_cpu_s=sum(s.worker_cpu_s for s in stats),
    )
    if all(isinstance(c, CompactChunk) for c in chunks):
        return CompactChunk.concatenate(chunks).expand(), total
    return concatenate([c.expand() if isinstance(c, CompactChunk) else c for c in chunks]), total


def generate_data(
    system: System,
    seed: int | np.random.SeedSequence,
    n_simulations: int,
    *,
    settings: ExecutionSettings | None = None,
    progress: Callable[[int], None] | None = None,
    **options,
) -> tuple[Dataset, GenerationStats]:
    """Alg. 2 over ``n_simulations`` simulations in fixed-size chunks; ``options`` are those of
    `generation_tasks` (time_weight, dt, max_cost, max_state_distance, chunk_size, u_max,
    max_duration, goal_simulations, goal).

    The dataset depends on the seed only: neither on ``chunk_size``, nor on the backend or
    the number of workers (``settings``). ``progress(k)`` is called with the number of
    simulations of each finished chunk.
    """
    tasks = generation_tasks(system, seed, n_simulations, **options)
    parts = map_tasks(run_generation_task, tasks, settings,
                      None if progress is None else lambda i, r: progress(tasks[i].count))
    return merge(parts)
