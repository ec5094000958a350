"""Held-out evaluation of the learned functions (paper Experiments: steering MSE)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.integrate import rollout
from rrtcolearn.learn.models import LearnedFunctions
from rrtcolearn.systems.base import System


@dataclass(frozen=True)
class HeldOutErrors:
    """Per-query errors on held-out (x0, x1) pairs that V accepts."""

    steer_mse: np.ndarray  # (Q,) mean over coordinates of the squared error to x1
    cost_rel_error: np.ndarray  # (Q,) |J_hat - J| / J
    param_error: np.ndarray  # (Q,) error of the costate parameters (circular ones on the circle)
    duration_error: np.ndarray  # (Q,) |T_hat - T|
    accepted_fraction: float  # share of the sampled held-out queries V accepted


def held_out_errors(system: System, functions: LearnedFunctions, held_out: Dataset, *,
                    n_queries: int = 1000, time_weight: float = 1.0, dt: float = 0.01,
                    seed: int = 0) -> HeldOutErrors:
    """Simulate from x0 with the *predicted*, unperturbed steering parameters.

    The paper's 0.11 is the median of this error; queries whose predicted costate does not
    exist (negative square root) count as failures with an infinite error.
    """
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(held_out))
    X = held_out.inputs[order]
    cost, steer, valid = functions.query(X)
    accepted = np.flatnonzero(valid)
    pick = accepted[:n_queries]
    n = system.n_states
    mse = np.empty(len(pick))
    for q, i in enumerate(pick):  # one rollout per query: the compiled kernel does the work
        lam, ok = system.costate_from_params(X[i : i + 1, :n], steer[i : i + 1, :-1],
                                             time_weight)
        if not ok[0]:
            mse[q] = np.inf
            continue
        steps = max(1, round(steer[i, -1] / dt))
        traj = rollout(system, np.r_[X[i, :n], lam[0], 0.0], time_weight, dt, steps)
        mse[q] = np.mean((traj[-1, :n] - X[i, n:]) ** 2)
    true_cost = held_out.cost[order][pick]
    true_params = held_out.params[order][pick]
    diff = np.abs(steer[pick, :-1] - true_params)
    period = system.param_high - system.param_low
    circ = np.asarray(system.param_circular, dtype=bool)
    diff[:, circ] = np.minimum(diff[:, circ], period[circ] - diff[:, circ])
    return HeldOutErrors(mse, np.abs(cost[pick] - true_cost) / true_cost,
                         np.linalg.norm(diff, axis=1),
                         np.abs(steer[pick, -1] - held_out.duration[order][pick]),
                         len(accepted) / len(X))
