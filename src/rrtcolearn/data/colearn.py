"""Data where the planner needs it: the co-learning loop after a first uniform batch.

Each round samples (x0, x1) pairs the way the planner asks for them (x0 a state the data's
trajectories pass, x1 a target within the data's reach of it), finds those the learned
steering fails on (V rejects the pair, or U's steering integrated from x0 lands farther from
x1 than the tolerance: the median landing error of round 0's functions on the held-out pairs
V accepts, so that round 0 hits about half of those), and starts optimal extremals at the failed x0
with costate parameters near U's guess (on H* = 0 through the system's parametrisation);
every RK4 step of them is a data point (Alg. 2). The functions are refitted and the hit rate
(share of a fixed held-out sample of pairs that V accepts and that land) measured; the loop
stops once a round raised it by less than `MIN_GAIN`, or after the configured rounds.

Deterministic per seed: round k draws from its own stream (the seed's spawn key extended by
(2, k)); a round's data and record are written atomically under ``store`` once finished, so
a killed run resumes from its last finished round to the same result.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.data.generate import _fresh, concatenate, simulate_from
from rrtcolearn.data.store import load_dataset, read_json, save_dataset, write_json
from rrtcolearn.errors import ArtefactError
from rrtcolearn.evaluate import landing_states
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems.base import System

MIN_GAIN = 0.01  # stop once a round raised the hit rate by less (absolute share)
PARAM_SPREAD = 0.05  # std of the aimed parameters around U's guess, share of their range
HELD_PAIRS = 400  # held-out pairs the hit rate is measured on


@dataclass(frozen=True)
class RoundRecord:
    """One round of the loop (round 0: the uniform data alone)."""

    round: int
    simulations: int  # aimed simulations of this round
    points: int  # data points they gave
    failures: int  # of the round's sampled pairs, those the steering failed on
    hit_rate: float  # on the held-out pairs, after refitting with this round's data
    tolerance: float  # the landing tolerance (plain norm), fixed by round 0
    shot: int  # aimed starts that Newton shooting took onto their x1 (``shooting``)
    cpu_s: float  # CPU of the round in this process (0 for a round loaded from the store)


def _stream(seed: int | np.random.SeedSequence, *key: int) -> np.random.Generator:
    root = _fresh(seed)
    return np.random.default_rng(np.random.SeedSequence(root.entropy,
                                                        spawn_key=(*root.spawn_key, *key)))


def sample_pairs(system: System, data: Dataset, rng: np.random.Generator, n: int,
                 reach: float) -> np.ndarray:
    """Queries (n, 2n_states) as a planner asks them: x0 a state along the data's
    trajectories (a data point's x1, as tree nodes lie along extremals), x1 = x0 plus an
    offset in a uniform direction with a length uniform in [0, reach) (the data's reach,
    the plain norm that stops Alg. 2's simulations), its bounded coordinates clipped to the
    box."""
    ns = system.n_states
    x0 = data.x1[rng.integers(0, len(data), n)]
    d = rng.standard_normal((n, ns))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x1 = x0 + d * (reach * rng.random(n))[:, None]
    b = system.bounded_dims
    x1[:, b] = np.clip(x1[:, b], system.state_low[b], system.state_high[b])
    return np.hstack([x0, x1])


def landing_errors(system: System, functions: LearnedFunctions, X: np.ndarray, *,
                   time_weight: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(landing error (Q,), V's acceptance (Q,), U's guess (Q, k+1)) of queries X: the plain
    distance from x1 at which U's unperturbed steering from x0 ends
    (`evaluate.landing_states`); inf where V rejects the pair or the rollout has no finite
    end."""
    ns = system.n_states
    _, steer, valid = functions.query(X)
    err = np.full(len(X), np.inf)
    rows = np.flatnonzero(valid)
    if rows.size:
        landed = landing_states(system, X[rows, :ns], steer[rows], time_weight, dt)
        e = np.linalg.norm(landed - X[rows, ns:], axis=1)
        err[rows] = np.where(np.isfinite(e), e, np.inf)
    return err, valid, steer


def median_landing(err: np.ndarray) -> float:
    """The landing tolerance: the median finite landing error (inf when there is none)."""
    finite = err[np.isfinite(err)]
    return float(np.median(finite)) if finite.size else float("inf")


def aimed_starts(system: System, x0: np.ndarray, guess: np.ndarray, rng: np.random.Generator,
                 time_weight: float, exact: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x0, p, lam, valid): parameters near U's guess (``guess`` (S, k), each perturbed by
    `PARAM_SPREAD` of its range; circular ones wrapped, the others clipped to their range)
    and their costates on H* = 0 at ``x0``. Rows where ``exact`` (S,) is True keep their
    guess unperturbed (parameters shooting found)."""
    low, high = system.param_low, system.param_high
    span = high - low
    g = np.where(np.isfinite(guess), guess, low + span * rng.random(guess.shape))
    noise = PARAM_SPREAD * span * rng.standard_normal(g.shape)
    if exact is not None:
        noise[exact] = 0.0
    p = g + noise
    circ = np.asarray(system.param_circular, dtype=bool)
    p[:, circ] = low[circ] + np.mod(p[:, circ] - low[circ], span[circ])
    p[:, ~circ] = np.clip(p[:, ~circ], low[~circ], high[~circ])
    lam, valid = system.costate_from_params(x0, p, time_weight)
    return x0, p, lam, valid


def colearn(system: System, data: Dataset, refit: Callable[[Dataset], LearnedFunctions], *,
            seed: int | np.random.SeedSequence, rounds: int, simulations: int, first_id: int,
            time_weight: float, dt: float, max_cost: float, max_state_distance: float,
            u_max: float | None = None, max_duration: float = 20.0,
            store: str | Path | None = None, stop_after: int | None = None,
            shooting: bool = False) -> tuple[Dataset, list[RoundRecord]]:
    """The loop (module docstring) from the uniform ``data``: up to ``rounds`` rounds of
    ``simulations`` aimed simulations each (ids from ``first_id``), ``refit(data)`` giving
    the functions of a dataset. Returns the uniform data with every finished round's and
    the records of rounds 0..k. ``store``: a directory keeping finished rounds (resume);
    ``stop_after``: return after that many rounds of this call (an interruption, for tests);
    ``shooting``: first refine U's guess for each failed pair by Newton shooting
    (`planning.shooting.shoot`, to 1% of the reach, at most 10 steps) and start the
    simulation unperturbed where it lands (the pair itself is then a data point).
    """
    reach, tol = max_state_distance, None
    store = Path(store) if store is not None else None
    held = sample_pairs(system, data, _stream(seed, 2, 0), HELD_PAIRS, reach)
    sim = {"time_weight": time_weight, "dt": dt, "max_cost": max_cost,
           "max_state_distance": max_state_distance, "u_max": u_max,
           "max_duration": max_duration}
    parts, records, functions, computed = [data], [], None, 0
    for k in range(rounds + 1):
        saved = _load_round(store, k, system.name)
        if saved is not None:
            aimed, record = saved
            if aimed is not None:
                parts.append(aimed)
            records.append(record)
            tol = record.tolerance
            functions = None  # of an earlier dataset
        else:
            if stop_after is not None and computed >= stop_after:
                break
            cpu0 = time.process_time()
            aimed = None
            failures = shot = 0
            if k > 0:
                rng = _stream(seed, 2, k)
                functions = functions or refit(concatenate(parts))
                X = sample_pairs(system, concatenate(parts), rng, 4 * simulations, reach)
                err, _, steer = landing_errors(system, functions, X,
                                               time_weight=time_weight, dt=dt)
                failed = np.flatnonzero(~(err <= tol))
                failures = int(failed.size)
                if failed.size == 0:
                    break
                pick = failed[np.arange(simulations) % failed.size]
                guess = steer[pick, :-1].copy()
                exact = np.zeros(len(pick), dtype=bool)
                if shooting:
                    exact = _shoot(system, X[pick], steer[pick], guess, time_weight, dt,
                                   max_duration, 0.01 * reach)
                shot = int(exact.sum())
                x0, p, lam, valid = aimed_starts(system, X[pick, :system.n_states],
                                                 guess, rng, time_weight, exact)
                ids = first_id + (k - 1) * simulations + np.flatnonzero(valid)
                chunk, _ = simulate_from(system, x0[valid], p[valid], lam[valid], ids, **sim)
                aimed = chunk.expand()
                parts.append(aimed)
            functions = refit(concatenate(parts))
            err, _, _ = landing_errors(system, functions, held, time_weight=time_weight,
                                       dt=dt)
            if tol is None:
                tol = median_landing(err)
            record = RoundRecord(k, simulations if k else 0, len(aimed) if aimed else 0,
                                 failures, float(np.mean(err <= tol)), tol, shot,
                                 time.process_time() - cpu0)
            _save_round(store, k, aimed, record, system.name)
            records.append(record)
            computed += 1
        if k > 0 and records[-1].hit_rate < records[-2].hit_rate + MIN_GAIN:
            break
    return concatenate(parts), records


def _shoot(system: System, X: np.ndarray, steer: np.ndarray, guess: np.ndarray,
           time_weight: float, dt: float, max_duration: float, tolerance: float
           ) -> np.ndarray:
    """Newton shooting from U's guess for each pair (first occurrence only); writes the
    parameters found into ``guess`` and returns where it landed."""
    from rrtcolearn.planning.shooting import shoot

    ns = system.n_states
    exact = np.zeros(len(X), dtype=bool)
    seen = set()
    for i in range(len(X)):
        key = X[i].tobytes()
        if key in seen or not np.all(np.isfinite(steer[i])) or steer[i, -1] <= 0:
            continue
        seen.add(key)
        target = X[i, ns:]
        res = shoot(system, X[i, :ns], steer[i, :-1], float(steer[i, -1]),
                    lambda s, t=target: s - t, time_weight=time_weight, dt=dt,
                    max_duration=max_duration, tolerance=tolerance, max_iterations=10)
        if res is not None and np.all(np.isfinite(res.params)):
            guess[i], exact[i] = res.params, True
    return exact


def _round_paths(store: Path, k: int) -> tuple[Path, Path]:
    return store / f"round-{k:03d}.json", store / f"round-{k:03d}.npz"


def _save_round(store: Path | None, k: int, aimed: Dataset | None, record: RoundRecord,
                system: str) -> None:
    """The round's data, then its record (written last: a record means a finished round)."""
    if store is None:
        return
    store.mkdir(parents=True, exist_ok=True)
    meta, arrays = _round_paths(store, k)
    if aimed is not None:
        save_dataset(arrays, aimed, {"system": system, "round": k})
    write_json(meta, asdict(record))


def _load_round(store: Path | None, k: int, system: str
                ) -> tuple[Dataset | None, RoundRecord] | None:
    """A finished round from the store (its CPU counted as 0: not spent by this call)."""
    if store is None:
        return None
    meta, arrays = _round_paths(store, k)
    try:
        record = RoundRecord(**{**read_json(meta), "cpu_s": 0.0})
        aimed = load_dataset(arrays, system)[0] if k > 0 else None
    except (ArtefactError, OSError, TypeError):
        return None
    return aimed, record
