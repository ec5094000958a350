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
