"""The `System` description: dynamics, cost and Pontryagin machinery of one control system."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class System:
    """An input-affine control system with running cost ``w + u^T R u / 2``.

    The steering parameters of an edge are the costate parameters (``param_names``) plus the
    duration; the costate at the edge start is a function of the start state and those
    parameters that satisfies H* = 0 by construction (paper Eq. 8).

    Attributes
    ----------
    name : registry name.
    state_names, input_names : coordinate names, ``n`` and ``m`` of them.
    state_low, state_high : (n,) box that start states are sampled from (paper: Experiments).
    angle_dims : state coordinates that are angles with period 2*pi (the dynamics are
        periodic in them, so queries may be shifted by whole turns).
    param_names, param_low, param_high : costate parameters and their sampling domain.
    param_circular : which parameters live on a circle of period ``param_high - param_low``.
    rhs : compiled ``rhs(z, w, out)`` for ``z = (x, lambda, cost)`` of length ``2n+1``:
        the state+costate ODE under u* and the running cost as the last entry.
    rollout_jit, rollout_batch_jit : the RK4 kernels of ``integrate`` compiled for ``rhs``.
    input_max_abs_jit : compiled ``z -> max_i |u*_i|`` at ``z``.
    costate_from_params : ``(x (N,n), p (N,k), w) -> (lambda (N,n), valid (N,))``.
    costate_from_params_jit : compiled scalar version for one state, used by the planner.
    optimal_control : ``(x (N,n), lambda (N,n)) -> u* (N,m)``, u* = argmin_u H.
    hamiltonian : ``(x, lambda, u, w) -> H (N,)``.
    dynamics : ``(x (N,n), u (N,m)) -> x' (N,n)``, the plain dynamics (for planners that
        choose inputs directly, and for independent checks).
    defaults : default query (``start``, ``goal``, optionally its goal region ``goal_fn`` and
        ``goal_sampler``, see `PlanningProblem`) and ``config``, the system's recommended
        configuration (nested dict, applied under the user's configuration).
    input_scale : (n,) weights of the state coordinates in learning distances (see
        `metric_scale`); None for the box-derived default.
    params_from_costate : ``(x (N,n), lambda (N,n)) -> p (N,k)``, the inverse of
        ``costate_from_params`` on H* = 0 (needed for data simulated backwards from a goal,
        whose costate is known only at the far end); None if the system has none.
    propagate_jit : compiled RK4 of ``dynamics`` from ``x0`` under a batch of constant
        inputs, each held for its number of steps and stopped at the state constraints
        (`rrtcolearn.integrate.propagate_draws`, `rrtcolearn.integrate.propagate`).
    closed_loop_jit : compiled RK4 of ``dynamics`` under a saturated affine feedback, constant
        or one per step: the goal connections' loops (`rrtcolearn.planning.lqr.GoalLQR.run`,
        `rrtcolearn.planning.lqr.GoalLQ.run`).
    hold_jit : compiled RK4 of ``dynamics`` under one held input into the caller's buffers
        (the OMPL peers' propagator, `rrtcolearn.baselines.ompl_planners`).
    rollout_draws_jit : compiled `rollout_jit` of a batch of costates from one state, checked
        (`rrtcolearn.integrate.rollout_draws`).
    explore_jit : the planner's random-control iterations compiled with ``dynamics``
        (`rrtcolearn.planning.controls.RandomControls.run_batch`).
    input_low, input_high : (m,) box of the inputs (+-inf where unbounded; None: no limits).
        With limits, u* is the minimiser of H over the box and every kernel above uses it
        (saturated optimal control, `rrtcolearn.systems.symbolic.limit_derivation`).
    invariant_coordinates : sorted state indices i on which nothing of the optimal control
        problem depends (a(x), B(x), hence H*, the state+costate ODEs and the running cost,
        and the costate parametrisation): shifting x0 and x1 together along such a
        coordinate leaves J and U unchanged, so they are learned on x1_i - x0_i there
        (`rrtcolearn.learn.features`). Found from the sympy model by `build_system`
        (`rrtcolearn.systems.symbolic.invariant_coordinates`); () for a system given as
        numeric callables only, whose invariances cannot be proven.
    planar_rotation : ``(i, j, k)`` when rotating the plane of the invariant coordinates
        (x_i, x_j) by phi and adding phi to the heading x_k maps solutions to solutions, and
        the steering parameters are the default costate direction (whose (i, j) components
        then rotate too): J and the duration are invariant, and U equivariant, under that
        rotation, so the learners see the query in x0's body frame
        (`rrtcolearn.learn.features`). Found exactly from the sympy model by `build_system`
        (`rrtcolearn.systems.symbolic.planar_rotation`); () otherwise.
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    state_low: np.ndarray
    state_high: np.ndarray
    angle_dims: tuple[int, ...]
    param_names: tuple[str, ...]
    param_low: np.ndarray
    param_high: np.ndarray
    param_circular: tuple[bool, ...]
    rhs: Callable
    rollout_jit: Callable
    rollout_batch_jit: Callable
    input_max_abs_jit: Callable
    costate_from_params: Callable
    costate_from_params_jit: Callable
    optimal_control: Callable
    hamiltonian: Callable
    dynamics: Callable
    description: str = ""
    defaults: dict = field(default_factory=dict)
    input_scale: np.ndarray | None = None
    params_from_costate: Callable | None = None
    input_low: np.ndarray | None = None
    input_high: np.ndarray | None = None
    propagate_jit: Callable | None = None
    closed_loop_jit: Callable | None = None
    rollout_draws_jit: Callable | None = None
    hold_jit: Callable | None = None
    explore_jit: Callable | None = None
    invariant_coordinates: tuple[int, ...] = ()
    planar_rotation: tuple[int, ...] = ()

    @property
    def metric_scale(self) -> np.ndarray:
        """(n,) weights of the state coordinates in every learning distance.

        ``input_scale`` if given, else ``2*pi / (state_high - state_low)``: each coordinate's
        sampling range counts as much as a full turn of an angle. The pendulum's ranges are
        both 2*pi, so its weights are exactly 1 and its distances the paper's Euclidean ones.
        """
        if self.input_scale is not None:
            return np.asarray(self.input_scale, dtype=np.float64)
        return 2.0 * np.pi / (self.state_high - self.state_low)

    @property
    def input_limited(self) -> bool:
        """Whether some input has a finite limit (the optimal control saturates)."""
        return bool(
            (self.input_low is not None and np.any(np.isfinite(self.input_low)))
            or (self.input_high is not None and np.any(np.isfinite(self.input_high))))

    def input_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(m,) lower and upper input bounds, +-inf where unbounded."""
        m = self.n_inputs
        low = np.full(m, -np.inf) if self.input_low is None else np.asarray(self.input_low, float)
        high = np.full(m, np.inf) if self.input_high is None else np.asarray(self.input_high,
                                                                              float)
        return low, high

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def n_inputs(self) -> int:
        return len(self.input_names)

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def bounded_dims(self) -> np.ndarray:
        """Indices of the state coordinates that are not angles."""
        return np.array([j for j in range(self.n_states) if j not in self.angle_dims], dtype=int)

    def wrap_shift(self, x: np.ndarray) -> np.ndarray:
        """Shift (N, n) states by whole turns so angle coordinates lie in the sampling box.

        Returns the (N, n) shift that was added; adding the same shift to a paired target keeps
        the optimal control problem unchanged because the dynamics are 2*pi-periodic in angles.
        """
        x = np.atleast_2d(x)
        shift = np.zeros_like(x)
        for j in self.angle_dims:
            lo = self.state_low[j]
            shift[:, j] = -2.0 * np.pi * np.floor((x[:, j] - lo) / (2.0 * np.pi))
        return shift


# The dynamics' fingerprint (`dynamics_probe`): the plain dynamics and the Hamiltonian at this
# many fixed states, inputs and costates, recorded in every dataset and model and compared
# on load to within this, relative to 1 + |value| (a rebuild's rounding, not a change)
PROBE_POINTS = 4
PROBE_TOLERANCE = 1e-9


def dynamics_probe(system: System) -> dict:
    """The values that tie data and models to ``system``'s dynamics and running cost: f(x, u)
    and H(x, lambda, u, w = 1) at `PROBE_POINTS` states drawn in its state box, inputs in its
    input box (where finite; else in [-1, 1]) and costates in [-1, 1], with those points.

    Why: a system is known by its name only; a definition edited after a fit (another mass,
    another gravity) keeps the name, and its model would plan with dynamics it never learned
    (edges that end elsewhere than the learned steering aims them). The points are stored
    with the values (JSON), so a check does not depend on how they were drawn."""
    n, m = system.n_states, system.n_inputs
    q = np.random.default_rng(0x70726F6265).random((PROBE_POINTS, 2 * n + m))  # ("probe")
    x = system.state_low + q[:, :n] * (system.state_high - system.state_low)
    low, high = system.input_limits()
    finite = np.isfinite(low) & np.isfinite(high)
    centre = np.where(finite, 0.5 * (low + high), 0.0) if finite.any() else np.zeros(m)
    half = np.where(finite, 0.5 * (high - low), 1.0) if finite.any() else np.ones(m)
    u = centre + (2.0 * q[:, n : n + m] - 1.0) * half
    lam = 2.0 * q[:, n + m :] - 1.0
    f, h = _probe_values(system, x, u, lam)
    return {"x": x.tolist(), "u": u.tolist(), "costate": lam.tolist(), "f": f.tolist(),
            "H": h.tolist()}


def _probe_values(system: System, x: np.ndarray, u: np.ndarray, lam: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(all="ignore"):
        f = np.asarray(system.dynamics(x, u), dtype=np.float64)
        h = np.asarray(system.hamiltonian(x, lam, u, 1.0), dtype=np.float64).reshape(-1)
    return f, h


def dynamics_mismatch(system: System, probe: object) -> str | None:
    """None when ``system`` gives the values of ``probe`` (a `dynamics_probe`, read from a
    file); else what differs, as a sentence."""
    n, m = system.n_states, system.n_inputs
    try:
        x, u, lam, f, h = (np.asarray(probe[k], dtype=np.float64)  # type: ignore[index]
                           for k in ("x", "u", "costate", "f", "H"))
    except (TypeError, KeyError, ValueError):
        return "its record of the dynamics is unreadable"
    k = len(x)
    if x.shape != (k, n) or u.shape != (k, m) or lam.shape != (k, n) or f.shape != (k, n) \
            or h.shape != (k,) or k == 0:
        return (f"it records dynamics of {x.shape[-1] if x.ndim == 2 else '?'} states and "
                f"{u.shape[-1] if u.ndim == 2 else '?'} inputs, the system has {n} and {m}")
    f_now, h_now = _probe_values(system, x, u, lam)
    for name, old, new in (("the dynamics f(x, u)", f, f_now),
                           ("the running cost (the Hamiltonian)", h, h_now)):
        gap = np.abs(new - old) / (1.0 + np.abs(old))
        if not np.all(gap <= PROBE_TOLERANCE):  # (NaN counts as a difference)
            i = int(np.unravel_index(np.argmax(np.where(np.isfinite(gap), gap, np.inf)),
                                     gap.shape)[0])
            return (f"{name} differ: at x = {np.round(x[i], 4).tolist()}, "
                    f"u = {np.round(u[i], 4).tolist()} it recorded "
                    f"{np.round(np.atleast_1d(old[i]), 6).tolist()}, the system gives "
                    f"{np.round(np.atleast_1d(new[i]), 6).tolist()}")
    return None
