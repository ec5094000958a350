"""Settings derived from the system and its data, so that a user's own problem runs with no
hand-picked learner or planner settings.

Every setting below defaults to None in the configuration ("derive it"); a value the user
gives is kept. Each derivation returns a `Choice` (key, value, reason) that the run summary
prints and ``config.toml`` records, so a run shows what was chosen and why. The rules and
the measurements behind them are in docs/derived_settings.md.

- ``generate.max_cost`` (Alg. 2's cost bound): the 90% quantile of the cost at which a pilot
  of simulations, run without a cost bound, first leaves the data's reach ball: nine in ten
  simulations stop by distance, and the bound cuts only the slow tail (4.5 on the paper's
  pendulum, whose bound is 2: 100% of swing-ups there at 0.85x the CPU; the median, 2.1,
  left the 4-state cart-pole's segments too short to swing up, 0 of 20).
- ``generate.n_simulations``: the paper's 40 000 for two states, times 2.5 per added pair of
  states (100 000 for four, the figure measured on the four-state systems).
- ``learn.validity_threshold``: a quantile of the summed distance from held-out valid pairs
  (whole simulations left out of the index) to their m nearest data pairs: V then accepts
  that share of queries as well covered as the data's own. The paper's 0.5 is the 96.6%
  quantile on its pendulum data; the rule takes 97%.
- ``learn.learner``: k-NN (the paper) up to two states, the neural networks above (their
  J error on the four-state systems is a fraction of k-NN's) when scikit-learn is installed.
- ``plan.sigma``/``plan.sigma_goal``: an eighth and a quarter of the steering parameters'
  mean range (the paper's pi/4 and pi/2 on its 2 pi range).
- ``plan.control_samples``: one draw where a single steering parameter pins the edge (the
  paper's planner), 16 with more.
- ``learn.invariant_coordinates`` (recorded, not a setting): the state coordinates J and U
  are learned on the difference x1 - x0 of, found in the sympy model
  (`System.invariant_coordinates`, docs/invariance.md).
- ``learn.planar_rotation`` (recorded, not a setting): the position pair and heading whose
  rotation the dynamics are equivariant under, so the learners see the query in x0's body
  frame (`System.planar_rotation`, docs/invariance.md).
- ``plan.extend_distance``: off (the paper's planner) where a uniform target lies within
  the data's reach of a node often enough (>= 10% from the box centre); else a third of the
  reach (the 4-state systems' measured 0.5), so that random targets stay within the
  segments the data hold. Distances are weighted by ``System.metric_scale``, as Alg. 2's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from rrtcolearn.systems.base import System

if TYPE_CHECKING:
    from rrtcolearn.learn.features import QueryFeatures

VALIDITY_QUANTILE = 0.97
COST_QUANTILE = 0.9
PILOT_SIMULATIONS = 1000
HELD_OUT_QUERIES = 5000
EXTEND_MIN_COVERAGE = 0.10


@dataclass(frozen=True)
class Choice:
    """One derived setting: the configuration key, its value, and why."""

    key: str
    value: Any
    reason: str

    @property
    def text(self) -> str:
        """"value: reason", as the run summary and ``config.toml`` show it."""
        return f"{_fmt(self.value)}: {self.reason}"


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def n_simulations(system: System) -> Choice:
    """Alg. 2's simulations per epoch from the state dimension."""
    n = system.n_states
    value = int(round(40_000 * 2.5 ** ((n - 2) / 2) / 1000) * 1000)
    return Choice("generate.n_simulations", value,
                  f"40 000 for 2 states x 2.5 per added pair of states ({n} states)")


def learner(system: System) -> Choice:
    """k-NN for up to two states, the networks above when scikit-learn is importable."""
    if system.n_states <= 2:
        return Choice("learn.learner", "knn", f"{system.n_states} states: k-NN (the paper)")
    try:
        import sklearn  # noqa: F401
    except ImportError:
        return Choice("learn.learner", "knn", f"{system.n_states} states would take the "
                      "networks, but scikit-learn is not installed (pip install "
                      "'rrtcolearn[mlp]')")
    return Choice("learn.learner", "mlp", f"{system.n_states} states: neural J and U "
                  "(k-NN's error grows with the dimension)")


def planar_rotation(system: System) -> Choice:
    """The rotation the learners see the query through (`System.planar_rotation`), with
    why; a record of what the system's model shows, not a setting to override."""
    rot = tuple(getattr(system, "planar_rotation", ()))
    if not rot:
        return Choice("learn.planar_rotation", [], "none: no pair of invariant coordinates "
                      "rotates with a heading under the dynamics (or the costates are the "
                      "author's own parametrisation)")
    x, y, th = (system.state_names[i] for i in rot)
    return Choice("learn.planar_rotation", list(rot), f"({x}, {y}) turn with the heading "
                  f"{th}: J and U are learned in x0's body frame")


def invariant_coordinates(system: System) -> Choice:
    """The coordinates the learners see as differences (`System.invariant_coordinates`),
    with why; a record of what the system's model shows, not a setting to override."""
    inv = tuple(system.invariant_coordinates)
    if not inv:
        return Choice("learn.invariant_coordinates", [], "none: every state coordinate "
                      "enters the dynamics or the costate parametrisation (or the system "
                      "has no sympy model to show otherwise)")
    names = ", ".join(system.state_names[i] for i in inv)
    return Choice("learn.invariant_coordinates", list(inv), f"{names}: neither a(x), B(x) "
                  "nor the costate parametrisation depend on them, so J and U are learned "
                  "on x1 - x0 there")


def steering_sigmas(system: System) -> tuple[Choice, Choice]:
    """sigma and sigma_goal from the steering parameters' mean range."""
    span = float(np.mean(system.param_high - system.param_low))
    return (Choice("plan.sigma", span / 8, f"1/8 of the parameters' mean range {span:.4g}"),
            Choice("plan.sigma_goal", span / 4, f"1/4 of the parameters' mean range {span:.4g}"))


def control_samples(system: System) -> Choice:
    k = system.n_params
    value = 1 if k <= 1 else 16
    return Choice("plan.control_samples", value,
                  f"{k} steering parameter{'s' if k != 1 else ''}: "
                  + ("one draw (the paper's planner)" if value == 1
                     else "16 draws, the one ending nearest the target kept"))


def reach_coverage(system: System, max_state_distance: float, samples: int = 4096) -> float:
    """Share of uniform box states within ``max_state_distance`` (the data's reach, in the
    weighted metric Alg. 2 bounds it in) of the box centre, angles the short way round; a
    fixed-seed Monte Carlo estimate."""
    rng = np.random.default_rng(12345)
    x = rng.uniform(system.state_low, system.state_high, (samples, system.n_states))
    diff = x - 0.5 * (system.state_low + system.state_high)
    angles = list(system.angle_dims)
    if angles:
        diff[:, angles] = np.mod(diff[:, angles] + np.pi, 2.0 * np.pi) - np.pi
    diff *= system.metric_scale
    return float(np.mean(np.einsum("ij,ij->i", diff, diff) <= max_state_distance**2))


def extend_distance(system: System, max_state_distance: float) -> Choice:
    """Off where random targets often lie within reach, else a third of the reach (both in
    the weighted metric)."""
    share = reach_coverage(system, max_state_distance)
    if share >= EXTEND_MIN_COVERAGE:
        return Choice("plan.extend_distance", 0.0, f"off (the paper's planner): {share:.0%} "
                      "of the box lies within the data's reach of its centre")
    value = max_state_distance / 3.0
    return Choice("plan.extend_distance", value, f"a third of the data's reach: only "
                  f"{share:.1%} of the box lies within reach of its centre")


def funnel_duration(max_duration: float) -> Choice:
    """``plan.funnel_duration``: the data's longest extremal (``max_duration``), so the goal
    funnel's extremals are as long as U and J know them (the shipped cart-pole's first paths
    11.7x -> 5.5x its optimum against a fixed 3 s, docs/ablation.md)."""
    return Choice("plan.funnel_duration", float(max_duration),
                  "the data's longest extremal: the goal funnel's extremals as long as U and J "
                  "know them")


def plan_choices(plan: Any, system: System, max_state_distance: float) -> list[Choice]:
    """The derived planner settings that ``plan`` (a `config.PlanConfig` or the planner's
    settings) leaves open (None): the steering noise, control samples and target
    extension."""
    sigma, sigma_goal = steering_sigmas(system)
    wanted = {"sigma": lambda: sigma, "sigma_goal": lambda: sigma_goal,
              "control_samples": lambda: control_samples(system),
              "extend_distance": lambda: extend_distance(system, max_state_distance)}
    return [make() for key, make in wanted.items() if getattr(plan, key) is None]


def pilot_max_cost(system: System, *, time_weight: float, dt: float,
                   max_state_distance: float, max_duration: float,
                   seed: np.random.SeedSequence, u_max: float | None = None) -> Choice:
    """Alg. 2's cost bound: the `COST_QUANTILE` quantile of the cost at which pilot
    simulations (no cost bound) first leave the reach ball; simulations that never leave it
    within ``max_duration`` count as infinitely costly."""
    from rrtcolearn.data.generate import sample_starts
    from rrtcolearn.integrate import rollout_batch

    x0, _, lam, valid = sample_starts(system, seed, 0, PILOT_SIMULATIONS, time_weight)
    z0 = np.hstack([x0, lam, np.zeros((len(x0), 1))])[valid]
    steps = max(1, math.ceil(max_duration / dt))
    exit_cost = []
    for lo in range(0, len(z0), 100):  # bounded memory: (100, steps, n) per batch
        _, costs, lengths, nonfinite = rollout_batch(
            system, z0[lo : lo + 100], time_weight, dt, steps, 1e300, max_state_distance,
            system.n_states, u_max=u_max)
        left = (lengths > 0) & (lengths < steps) & ~nonfinite
        c = np.full(len(lengths), np.inf)
        c[left] = costs[np.flatnonzero(left), lengths[left] - 1]
        exit_cost.append(c)
    c = np.concatenate(exit_cost) if exit_cost else np.array([np.inf])
    with np.errstate(invalid="ignore"):  # between two infinite costs: nan, the fallback
        value = float(np.quantile(c, COST_QUANTILE))
    fallback = 2.0 * max(1.0, time_weight)
    if not math.isfinite(value) or value <= 0:
        return Choice("generate.max_cost", fallback, f"the paper's 2 max(1, w): fewer than "
                      f"{COST_QUANTILE:.0%} of {len(c)} pilot simulations left the reach ball")
    return Choice("generate.max_cost", value, f"{COST_QUANTILE:.0%} of {len(c)} pilot "
                  "simulations leave the reach ball below this cost "
                  f"({np.isfinite(c).mean():.0%} leave it at all)")


def validity_threshold(inputs: np.ndarray, simulation: np.ndarray, scale: np.ndarray,
                       n_neighbors: int, seed: np.random.SeedSequence,
                       periodic: tuple[tuple[int, float, float], ...] = (),
                       features: QueryFeatures | None = None) -> Choice:
    """V's threshold: the 97% quantile of the summed distance from held-out pairs to their
    m nearest pairs among the rest (a twentieth of the simulations held out, whole), in
    the learners' space (``features``, `rrtcolearn.learn.features.learning_geometry`;
    None: the raw queries)."""
    from rrtcolearn.learn.features import QueryFeatures
    from rrtcolearn.learn.models import _pad_periodic
    from rrtcolearn.learn.neighbours import NeighbourIndex

    rng = np.random.default_rng(seed)
    sims = np.unique(simulation)
    if len(sims) < 20:
        raise ValueError(f"the data hold {len(sims)} simulations, too few to derive "
                         "learn.validity_threshold: set it or generate more")
    held = rng.choice(sims, size=len(sims) // 20, replace=False)
    mask = np.isin(simulation, held)
    queries = np.flatnonzero(mask)
    if len(queries) > HELD_OUT_QUERIES:
        queries = np.sort(rng.choice(queries, HELD_OUT_QUERIES, replace=False))
    inputs = np.asarray(inputs, dtype=np.float64)
    if features is None:
        features = QueryFeatures(inputs.shape[1] // 2)
    feature_scale = features.scale(scale)
    train = inputs[~mask]
    q = features.transform(inputs[queries]) * feature_scale

    def quantile(train: np.ndarray) -> float:
        dist, _ = NeighbourIndex(features.transform(train) * feature_scale).query(
            q, n_neighbors)
        return float(np.quantile(dist.sum(axis=1), VALIDITY_QUANTILE))

    value = quantile(train)
    if periodic:  # rows across an angle seam are neighbours too (as in the fitted model)
        value = quantile(_pad_periodic(train, periodic, np.tile(scale, 2), value)[1])
    return Choice("learn.validity_threshold", value,
                  f"{VALIDITY_QUANTILE:.0%} of {len(q)} held-out pairs have their "
                  f"{n_neighbors} nearest data pairs within it")
