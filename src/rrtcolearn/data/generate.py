"""Alg. 2 (generate_data): sample start states, costates on H* = 0 and integrate.

Every intermediate RK4 step of a simulation is a data point (paper Section 3), and a
simulation stops when its cost exceeds ``max_cost`` or its state leaves the ball of radius
``max_state_distance`` around its start (paper Experiments: 2 and 1.5).
"""

from __future__ import annotations

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
    ns, k = system.n_states, system.n_params
    stride = 4 * -(-(ns + k) // 4)  # Philox yields 4 doubles per counter step
    bitgen = np.random.Philox(_fresh(seed))
    bitgen.advance(first * stride // 4)
    u = np.random.Generator(bitgen).random((n, stride))
    x0 = system.state_low + (system.state_high - system.state_low) * u[:, :ns]
    p = system.param_low + (system.param_high - system.param_low) * u[:, ns : ns + k]
    lam, valid = system.costate_from_params(x0, p, w)
    return x0, p, lam, valid


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
    n = system.n_states
    x0, p, lam, valid = sample_starts(system, seed, first_index, n_simulations, time_weight)
    sim_index = first_index + np.flatnonzero(valid)
    x0, p, lam = x0[valid], p[valid], lam[valid]
    z0 = np.hstack([x0, lam, np.zeros((len(x0), 1))])
    # cost >= w*t bounds every simulation's duration; max_duration caps it regardless
    max_steps = int(min(np.ceil(max_cost / (time_weight * dt)) + 1, np.ceil(max_duration / dt)))
    states, costs, lengths, nonfinite = rollout_batch(
        system, z0, time_weight, dt, max_steps, max_cost, max_state_distance, n, u_max=u_max,
    )
    mask = np.arange(max_steps)[None, :] < lengths[:, None]
    rows, steps = np.nonzero(mask)
    chunk = CompactChunk(x0=x0, params=p, costate=lam, simulation=sim_index.astype(np.int64),
                         point_sim=rows.astype(np.int32), x1=states[rows, steps],
                         cost=costs[rows, steps], step=(steps + 1).astype(np.int32), dt=dt)
    stats = GenerationStats(
        simulations=n_simulations,
        invalid_costates=int(n_simulations - valid.sum()),
        empty_simulations=int((lengths == 0).sum()),
        points=len(rows),
        nonfinite_simulations=int(nonfinite.sum()),
        worker_cpu_s=time.process_time() - cpu0,
    )
    return chunk, stats


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


def run_generation_task(task: GenerationTask) -> tuple[Dataset, GenerationStats]:
    """Generate one chunk (top-level so that worker processes can import it)."""
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
) -> list[GenerationTask]:
    """Alg. 2 split into chunks of ``chunk_size`` simulations (see `sample_starts`)."""
    if n_simulations < 1 or chunk_size < 1:
        raise ValueError("n_simulations and chunk_size must be positive")
    n_chunks = -(-n_simulations // chunk_size)
    root = _fresh(seed)
    return [
        GenerationTask(system, c, c * chunk_size,
                       min(chunk_size, n_simulations - c * chunk_size), root, time_weight, dt,
                       max_cost, max_state_distance, u_max, max_duration)
        for c in range(n_chunks)
    ]


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
    time_weight: float = 1.0,
    dt: float = 0.01,
    max_cost: float = 2.0,
    max_state_distance: float = 1.5,
    chunk_size: int = 2000,
    u_max: float | None = None,
    max_duration: float = 20.0,
    settings: ExecutionSettings | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[Dataset, GenerationStats]:
    """Alg. 2 over ``n_simulations`` simulations in fixed-size chunks.

    The dataset depends on the seed only: neither on ``chunk_size``, nor on the backend or
    the number of workers (``settings``). ``progress(k)`` is called with the number of
    simulations of each finished chunk.
    """
    tasks = generation_tasks(system, seed, n_simulations, time_weight=time_weight, dt=dt,
                             max_cost=max_cost, max_state_distance=max_state_distance,
                             chunk_size=chunk_size, u_max=u_max, max_duration=max_duration)
    parts = map_tasks(run_generation_task, tasks, settings,
                      None if progress is None else lambda i, r: progress(tasks[i].count))
    return merge(parts)
