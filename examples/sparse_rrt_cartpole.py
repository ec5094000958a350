"""sparse_rrt's cart-pole benchmark (`cart_pole`), typed in through `build_system` as a user would.

Source: sparse_rrt (Littlefield, Li, Bekris; its src/systems/cart_pole.cpp), the problem as
written out here and in docs/external_problems.md. State (x, v, theta, w), theta = pi
upright (unstable),
theta = 0 hanging; I = 10, L = 2.5, M = 10, m = 5, g = 9.8, force F on the cart:

    D  = (M + m)(I + m L^2) - m^2 L^2 cos^2(theta)
    x' = v,  theta' = w
    v' = ((I + m L^2)(F + m L w^2 sin theta) + m^2 L^2 cos theta sin theta g) / D
    w' = (-m L cos theta (F + m L w^2 sin theta) + (M + m)(-m g L sin theta)) / D

input-affine in F: B = (0, (I + m L^2) / D, 0, -m L cos theta / D). Limits |F| <= 300
(saturated optimal control), x in [-30, 30], v in [-40, 40], |w| <= 2. The sampling box is
those bounds with theta over one turn around the upright, [0, 2 pi]; R = 1 (identity) and the
default time weight. Query (a transfer with the pole held inverted, not a swing-up): start
(-20, 0, 3.14, 0), goal (20, 0, 3.14, 0), goal radius 1.5 in the plain Euclidean norm over
all four coordinates (`GOAL_RADIUS`; plan.wrap_goal stays false, as in sparse_rrt).

Differences from sparse_rrt that remain (docs/external_problems.md):
- sparse_rrt integrates with explicit Euler and clamps v and w to their bounds after every
  step (a saturation); rrtcolearn treats the box as a state constraint (an edge leaving it is
  invalid), which is stricter. `make_cartpole_wide` widens the velocity bounds by 50% for a
  sensitivity row.
- sparse_rrt's planner state box and its sampling box are one; here too (the planner's
  constraints could differ from the data's box through plan.state_low/high).

The query (tolerance 1.5, 60 s) is the system's default; every learner and planner setting
is derived by the library (docs/derived_settings.md). Run it (from the repository root, so
that `examples` is importable)::

    rrtcolearn run --system examples.sparse_rrt_cartpole:make_cartpole
"""

from __future__ import annotations

import math

import sympy

from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

PARAMETERS = {"I": 10.0, "L": 2.5, "M": 10.0, "m": 5.0, "g": 9.8}
FORCE_LIMIT = 300.0
X_BOUND, V_BOUND, W_BOUND = 30.0, 40.0, 2.0
START = [-20.0, 0.0, 3.14, 0.0]
GOAL = [20.0, 0.0, 3.14, 0.0]
GOAL_RADIUS = 1.5  # Euclidean over all four coordinates, no angle wrapping


def cartpole_equations():
    """(states, input, drift a(x), input matrix B(x), parameter symbols) as sympy objects."""
    x, v, th, w, f = sympy.symbols("x v theta w F", real=True)
    inertia, ell, big_m, m, g = sympy.symbols("I L M m g", positive=True)
    d = (big_m + m) * (inertia + m * ell**2) - m**2 * ell**2 * sympy.cos(th) ** 2
    spin = m * ell * w**2 * sympy.sin(th)  # the m L w^2 sin(theta) term added to F
    drift = [v,
             ((inertia + m * ell**2) * spin
              + m**2 * ell**2 * sympy.cos(th) * sympy.sin(th) * g) / d,
             w,
             (-m * ell * sympy.cos(th) * spin + (big_m + m) * (-m * g * ell * sympy.sin(th))) / d]
    input_matrix = [[0], [(inertia + m * ell**2) / d], [0], [-m * ell * sympy.cos(th) / d]]
    symbols = {"I": inertia, "L": ell, "M": big_m, "m": m, "g": g}
    return (x, v, th, w), f, drift, input_matrix, symbols


def _make(name: str, velocity_scale: float) -> SymbolicSystem:
    states, f, drift, input_matrix, symbols = cartpole_equations()
    vb, wb = V_BOUND * velocity_scale, W_BOUND * velocity_scale
    return build_system(
        name, states=states, inputs=[f], drift=drift, input_matrix=input_matrix,
        input_weight=[[1]],
        parameters={symbols[k]: v for k, v in PARAMETERS.items()},
        input_low=-FORCE_LIMIT, input_high=FORCE_LIMIT,
        state_low=[-X_BOUND, -vb, 0.0, -wb],
        state_high=[X_BOUND, vb, 2 * math.pi, wb],
        angle_dims=[2], state_names=["x", "v", "theta", "w"], input_names=["force"],
        description="sparse_rrt cart_pole (I 10, L 2.5, M 10, m 5), |F| <= 300, theta = pi up"
                    + ("" if velocity_scale == 1.0 else
                       f"; velocity bounds x{velocity_scale:g}"),
        # the query as sparse_rrt states it: radius 1.5, plain Euclidean over all coordinates
        defaults={"start": list(START), "goal": list(GOAL),
                  "config": {"plan": {"goal_tolerance": GOAL_RADIUS, "time_limit": 60.0}}},
    )


def make_cartpole() -> SymbolicSystem:
    """sparse_rrt's cart-pole with its stated bounds as the box and its transfer query."""
    return _make("sparse_rrt_cartpole", 1.0)


def make_cartpole_wide() -> SymbolicSystem:
    """The same with the velocity bounds widened by 50% (v in [-60, 60], |w| <= 3)."""
    return _make("sparse_rrt_cartpole_wide", 1.5)


if __name__ == "__main__":
    from rrtcolearn.systems.check import check_system

    system = make_cartpole()
    check_system(system)
    print(f"{system.name}: check_system passed; run it with\n  rrtcolearn run --system "
          "examples.sparse_rrt_cartpole:make_cartpole")
