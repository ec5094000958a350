"""Which predictor of the steering parameters lands best: U as the k nearest neighbours'
mean (today's), the nearest neighbour's parameters, the distance-weighted mean, the best of
the neighbours' parameters by a rollout, a ridge-regularised local linear regression over
more neighbours, and (``--mlp``) the network, on held-out pairs.

Per system (the data settings of the hashed cases, tests/tree_cases.py): the cleaned data
of a case's run in ``--models`` (fitted there first if missing) split by simulation, every
tenth held out; the functions refitted on the rest with the run's configuration. Two sets
of (x0, x1) queries that V accepts: held-out data rows (true extremals, so the parameter
error is known) and planner-like pairs (`data.colearn.sample_pairs`: x0 on the data's
trajectories, x1 a uniform offset within the data's reach). For each predictor: the median
landing distance |x(T) - x1| (angles the short way) over |x1 - x0| of the unperturbed
extremal from x0 (`evaluate.landing_states`), the shares landing within half the distance
(`learned.REFINE_PROGRESS`, refinement's gate) and within the refinement's landing tolerance
(`learned.LAND_FRACTION` of the plan's goal tolerance), the share a 6-iteration Newton
refinement from the prediction lands within that tolerance (`shooting.shoot`), and the
median parameter error (held-out rows; circular parameters on the circle, duration left
out), and the predictor's CPU per query; per set, the median of V's statistic (the summed
distance to the m nearest inputs) against its threshold.

    python bench/steering_predictors.py --models /tmp/i31c_models \
        [--cases pendulum_auto,sparse_rrt_cartpole,acrobot,cartpole,quadrotor] \
        [--queries 200] [--mlp]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).parents[1]
sys.path.insert(0, str(ROOT))

from bench.landing_ab import PROBLEMS  # noqa: E402

NEWTON_ITERATIONS = 6
HOLD_OUT_EVERY = 10  # simulations with id % this == 0 are held out


def _case_model(name: str, models: Path):
    from tests.tree_cases import CASES, fit_model, load_model

    case = next(c for c in CASES if c.name == name)
    target = models / name
    if (target / "model.json").exists():
        return case, load_model(case, target), target
    return case, fit_model(case, target), target


def _wrap(d: np.ndarray, angles: list[int]) -> np.ndarray:
    if angles:
        d = d.copy()
        d[:, angles] = np.mod(d[:, angles] + np.pi, 2.0 * np.pi) - np.pi
    return d


def _finish(fn, out: np.ndarray, dt: float, max_duration: float) -> np.ndarray:
    """Circular columns wrapped into their range, the others clipped to it, the duration to
    [dt, max_duration]."""
    st = fn.steering_
    c = st.circular_
    k = len(out[0]) - 1
    out = out.copy()
    low, period = st.low_, st.period_
    out[:, c] = low[c] + np.mod(out[:, c] - low[c], period[c])
    nc = ~c.copy()
    nc[k] = False
    out[:, nc] = np.clip(out[:, nc], low[nc], (low + period)[nc])
    out[:, k] = np.clip(out[:, k], dt, max_duration)
    return out


def _unwrapped(fn, Y: np.ndarray) -> np.ndarray:
    """Neighbours' targets Y (Q, K, k+1) with circular columns unwrapped around the nearest
    neighbour's value (so a line through them does not jump a branch cut)."""
    st = fn.steering_
    c = st.circular_
    if not c.any():
        return Y
    Y = Y.copy()
    ref = Y[:, :1, c]
    p = st.period_[c]
    Y[:, :, c] = ref + np.mod(Y[:, :, c] - ref + p / 2, p) - p / 2
    return Y


def predict_weighted(fn, dist: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Inverse-distance-weighted mean (circular columns unwrapped around the nearest)."""
    Y = _unwrapped(fn, fn.steering_.targets_[idx])
    w = 1.0 / np.maximum(dist, 1e-12)
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("qk,qkj->qj", w, Y)


def predictors(fn, X: np.ndarray, system, time_weight: float, dt: float, mlp=None) -> dict:
    """name -> (predicted parameters and duration (Q, k+1), CPU seconds per query)."""
    from rrtcolearn.evaluate import landing_states

    n = system.n_states
    F = fn.features_.transform(X)
    Fs = F * fn.input_scale_
    m = fn.n_neighbors
    d = Fs.shape[1]
    index = fn.cost_to_go_.index_
    out = {}

    def timed(name, f):
        t = time.process_time()
        p = f()
        out[name] = (p, (time.process_time() - t) / len(X))

    dist, idx = index.query(Fs, m)
    timed("mean", lambda: fn.steering_.predict_from_neighbours(dist, idx))
    timed("nearest", lambda: fn.steering_.targets_[index.query(Fs, 1)[1][:, 0]].copy())
    timed("weighted", lambda: predict_weighted(fn, *index.query(Fs, m)))

    def best_rollout():
        _, ii = index.query(Fs, m)
        cands = fn.steering_.targets_[ii]  # (Q, m, k+1)
        ends = np.stack([landing_states(system, X[:, :n], cands[:, j], time_weight, dt)
                         for j in range(m)], axis=1)
        err = np.linalg.norm(_wrap((ends - X[:, None, n:]).reshape(-1, n),
                                   list(system.angle_dims)), axis=1).reshape(len(X), m)
        err[~np.isfinite(err)] = np.inf
        return cands[np.arange(len(X)), np.argmin(err, axis=1)]

    timed("best_of_k_rollout", best_rollout)
    # the library's fit (`SteeringRegressor.predict_local`): neighbours K, ridge, clipped
    # to the neighbours' range or not
    for K, ridge, clip in ((2 * d + 1, 0.01, False), (4 * d, 0.01, False),
                           (4 * d, 0.1, False), (4 * d, 0.01, True), (4 * d, 0.1, True)):
        timed(f"local_linear_K{K}_r{ridge:g}{'_clipped' if clip else ''}",
              lambda K=K, ridge=ridge, clip=clip: fn.steering_.predict_local(
                  Fs, index.query(Fs, K)[1], ridge, clip))
    if mlp is not None:
        timed("mlp", lambda: mlp.steering_predict(X))
    return out


def measure(system, X: np.ndarray, pred: np.ndarray, true_params: np.ndarray | None, *,
            time_weight: float, dt: float, max_duration: float, land_tol: float) -> dict:
    from rrtcolearn.evaluate import landing_states
    from rrtcolearn.planning.shooting import shoot

    n = system.n_states
    angles = list(system.angle_dims)
    ends = landing_states(system, X[:, :n], pred, time_weight, dt)
    err = np.linalg.norm(_wrap(ends - X[:, n:], angles), axis=1)
    err[~np.isfinite(err)] = np.inf
    dist = np.linalg.norm(_wrap(X[:, n:] - X[:, :n], angles), axis=1)
    rel = err / np.maximum(dist, 1e-12)
    newton = 0
    for i in range(len(X)):
        target = X[i, n:]

        def offset(s, t=target):
            return _wrap(s - t, angles)
        if not np.isfinite(pred[i]).all():
            continue
        res = shoot(system, X[i, :n], pred[i, :-1], float(pred[i, -1]), offset,
                    time_weight=time_weight, dt=dt, max_duration=max_duration,
                    tolerance=land_tol, max_iterations=NEWTON_ITERATIONS)
        newton += res is not None
    row = {"rel_landing": float(np.median(rel)), "halfway": float(np.mean(rel <= 0.5)),
           "on_aim": float(np.mean(err <= land_tol)), "newton6": newton / len(X),
           "param_error": float("nan")}
    if true_params is not None:
        diff = np.abs(pred[:, :-1] - true_params)
        period = system.param_high - system.param_low
        circ = np.asarray(system.param_circular, dtype=bool)
        diff[:, circ] = np.minimum(diff[:, circ], period[circ] - diff[:, circ])
        row["param_error"] = float(np.median(np.linalg.norm(diff, axis=1)))
    return row


class _MLP:
    """U from networks fitted on the same training split (`LearnedFunctions(learner='mlp')`)."""

    def __init__(self, functions):
        self.functions = functions

    def steering_predict(self, X: np.ndarray) -> np.ndarray:
        return self.functions.query(X)[1]


def run_case(name: str, models: Path, n_queries: int, with_mlp: bool) -> list[dict]:
    from rrtcolearn import pipeline
    from rrtcolearn.data.colearn import sample_pairs
    from rrtcolearn.data.store import load_dataset
    from rrtcolearn.planning.learned import LAND_FRACTION

    _, model, run_dir = _case_model(name, models)
    system, cfg = model.system, model.config
    data, _ = load_dataset(run_dir / pipeline.CLEANED_FILE, system.name)
    held = data.simulation % HOLD_OUT_EVERY == 0
    train, test = data.take(~held), data.take(held)
    fn = pipeline.fit_functions(system, train, cfg)
    g = cfg.generate
    tw, dt = cfg.system.time_weight, g.dt
    max_duration = float(fn.max_duration_)
    # the goal tolerance bench/landing_ab.py plans with (the hashed case's is tighter)
    tol = next((q["goal_tolerance"] for c, q, _ in PROBLEMS.values()
                if c == name and "goal_tolerance" in q), cfg.plan.goal_tolerance)
    land_tol = LAND_FRACTION * tol
    mlp = None
    if with_mlp:
        t = time.process_time()
        cfg_mlp = cfg.model_copy(update={"learn": cfg.learn.model_copy(
            update={"learner": "mlp"})})
        mlp = _MLP(pipeline.fit_functions(system, train, cfg_mlp))
        print(f"{name}: mlp fitted in {time.process_time() - t:.1f} s CPU", flush=True)
    perm = np.random.default_rng(0).permutation(len(test))
    Xh = test.inputs[perm]
    _, _, ok = fn.query(Xh)
    pick = np.flatnonzero(ok)[:n_queries]
    sets = {"held-out rows": (Xh[pick], test.params[perm][pick])}
    Xp = sample_pairs(system, train, np.random.default_rng(1), 20 * n_queries,
                      g.max_state_distance)
    _, _, ok = fn.query(Xp)
    sets["planner pairs"] = (Xp[np.flatnonzero(ok)[:n_queries]], None)
    rows = []
    for set_name, (X, true) in sets.items():
        # how near the data each set's pairs are: V's statistic (the summed distance to the
        # m nearest, weighted) against its threshold
        dist, _ = fn.cost_to_go_.index_.query(fn.features_.transform(X) * fn.input_scale_,
                                              fn.n_neighbors)
        print(f"{name} ({set_name}): median summed distance to the {fn.n_neighbors} nearest "
              f"{np.median(dist.sum(axis=1)):.2f}, V's threshold "
              f"{fn.validity_.threshold:.2f}", flush=True)
        for pname, (pred, cpu) in predictors(fn, X, system, tw, dt, mlp).items():
            pred = _finish(fn, pred, dt, max_duration)
            r = measure(system, X, pred, true, time_weight=tw, dt=dt,
                        max_duration=max_duration, land_tol=land_tol)
            rows.append({"case": name, "set": set_name, "queries": len(X),
                         "predictor": pname, "cpu_us": 1e6 * cpu, **r})
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/steer_models"))
    ap.add_argument("--cases", default="pendulum_auto,sparse_rrt_cartpole,acrobot,cartpole,"
                                       "quadrotor")
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--mlp", action="store_true", help="also fit and measure the network")
    args = ap.parse_args()
    rows = [r for c in args.cases.split(",") for r in run_case(c, args.models, args.queries,
                                                               args.mlp)]
    print("\n| system | queries | predictor | landing / distance | within half | on aim "
          "| Newton (6) lands | parameter error | CPU per query (us) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} ({r['set']}) | {r['queries']} | {r['predictor']} | "
              f"{r['rel_landing']:.2f} | {100 * r['halfway']:.0f}% | {100 * r['on_aim']:.0f}% "
              f"| {100 * r['newton6']:.0f}% | {r['param_error']:.2f} | {r['cpu_us']:.0f} |")


if __name__ == "__main__":
    main()
