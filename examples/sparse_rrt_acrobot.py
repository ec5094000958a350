"""sparse_rrt's acrobot benchmark (`two_link_acrobot`), typed in through `build_system`.

Source: sparse_rrt (Littlefield, Li, Bekris; its src/systems/two_link_acrobot.cpp), the
model as sparse_rrt ships it, its "extra" terms included; the anchors (sparse_rrt's own SST
on this problem) are in docs/external_problems.md. State (theta1, theta2, theta1', theta2'),
theta1 = 0 hanging, both angles wrapping;
m = 1, l = 1, lc = 0.5, lc2 = 0.25, l2 = 1, I1 = 0.2, I2 = 1.0, g = 9.8, t1 = theta1 - pi/2,
t2 = theta2, elbow torque tau:

    d11 = m lc2 + m (l2 + lc2 + 2 l lc cos t2) + I1 + I2,   d22 = m lc2 + I2,
    d12 = d21 = m (lc2 + l lc cos t2) + I2
    c1 = -m l lc theta2'^2 sin t2 - 2 m l lc theta1' theta2' sin t2,  c2 = m l lc theta1'^2 sin t2
    g1 = (m lc + m l) g cos t1 + m lc g cos(t1 + t2),  g2 = m lc g cos(t1 + t2)
    u1 = -0.1 theta1',  u2 = tau - 0.1 theta2'
    theta1'' = (d22 (u1 - c1 - g1) - d12 (u2 - c2 - g2)) / (d11 d22 - d12 d21)
    theta2'' = (d11 (u2 - c2 - g2) - d21 (u1 - c1 - g1)) / (d11 d22 - d12 d21)

input-affine in tau: B = (0, 0, -d12, d11) / (d11 d22 - d12^2). It is a mechanical system
with mass matrix [[d11, d12], [d12, d22]] and potential V = (m lc + m l) g sin t1
+ m lc g sin(t1 + t2) (c1, c2 are its Christoffel terms), so E = q'^T D q' / 2 + V changes at
the rate theta2' tau - 0.1 (theta1'^2 + theta2'^2) (tests/test_external_problems.py).
Limits |tau| <= 4 (saturated optimal control), |theta1'|, |theta2'| <= 6; sampling box
theta1, theta2 in [-pi, pi] (sparse_rrt's wrapping interval) and the velocity bounds;
R = 1 (identity), default time weight.

The goal is sparse_rrt's: the end effector (x, y) = 20 (cos t1 + cos(t1 + t2), sin t1 +
sin(t1 + t2)) within distance 2 of the goal's (theta1 = 3.14, theta2 = 0), velocities free.
The system's default query carries it as a goal region (`task_goal_distance`, a distance the
plan's goal tolerance 2 bounds, and `sample_task_goal`, which draws states in the region for
the goal bias); `GOAL_RADIUS` is the largest state ball inside it (0.0447, angles wrapped), kept
for comparison.

Other differences: sparse_rrt clamps the velocities after every Euler step, rrtcolearn treats
the bounds as state constraints (`make_acrobot_wide` widens them by 50% for the sensitivity
row). Every learner and planner setting is derived by the library
(docs/derived_settings.md).

Run it (from the repository root, so that `examples` is importable)::

    rrtcolearn run --system examples.sparse_rrt_acrobot:make_acrobot
"""

from __future__ import annotations

import math

import numpy as np
import sympy

from rrtcolearn.systems.symbolic import SymbolicSystem, build_system

PARAMETERS = {"m": 1.0, "l": 1.0, "lc": 0.5, "lc2": 0.25, "l2": 1.0, "I1": 0.2, "I2": 1.0,
              "g": 9.8}
DAMPING = 0.1
TORQUE_LIMIT = 4.0
VELOCITY_BOUND = 6.0
START = [0.0, 0.0, 0.0, 0.0]
GOAL = [3.14, 0.0, 0.0, 0.0]
# largest Euclidean ball over all four coordinates (angles wrapped) inside sparse_rrt's goal
# region (end effector at L = 20 within 2 of the goal's); tests/test_external_problems.py
GOAL_RADIUS = 0.0447
LINK_LENGTH_TASK = 20.0
TASK_GOAL_RADIUS = 2.0


def acrobot_equations(damping: float = DAMPING):
    """(states, input, drift a(x), input matrix B(x), parameter symbols) as sympy objects;
    ``damping`` is the coefficient of the -damping * theta' terms in u1, u2."""
    q1, q2, dq1, dq2, tau = sympy.symbols("theta1 theta2 dtheta1 dtheta2 tau", real=True)
    m, ell, lc, lc2, l2, i1, i2, g = sympy.symbols("m l lc lc2 l2 I1 I2 g", positive=True)
    t1, t2 = q1 - sympy.pi / 2, q2
    d11 = m * lc2 + m * (l2 + lc2 + 2 * ell * lc * sympy.cos(t2)) + i1 + i2
    d22 = m * lc2 + i2
    d12 = d21 = m * (lc2 + ell * lc * sympy.cos(t2)) + i2
    c1 = -m * ell * lc * dq2**2 * sympy.sin(t2) - 2 * m * ell * lc * dq1 * dq2 * sympy.sin(t2)
    c2 = m * ell * lc * dq1**2 * sympy.sin(t2)
    g1 = (m * lc + m * ell) * g * sympy.cos(t1) + m * lc * g * sympy.cos(t1 + t2)
    g2 = m * lc * g * sympy.cos(t1 + t2)
    u1 = -damping * dq1
    u2_free = -damping * dq2  # u2 = tau + u2_free
    det = d11 * d22 - d12 * d21
    drift = [dq1, dq2,
             (d22 * (u1 - c1 - g1) - d12 * (u2_free - c2 - g2)) / det,
             (d11 * (u2_free - c2 - g2) - d21 * (u1 - c1 - g1)) / det]
    input_matrix = [[0], [0], [-d12 / det], [d11 / det]]
    symbols = {"m": m, "l": ell, "lc": lc, "lc2": lc2, "l2": l2, "I1": i1, "I2": i2, "g": g}
    return (q1, q2, dq1, dq2), tau, drift, input_matrix, symbols


def _make(name: str, velocity_scale: float) -> SymbolicSystem:
    states, tau, drift, input_matrix, symbols = acrobot_equations()
    vb = VELOCITY_BOUND * velocity_scale
    return build_system(
        name, states=states, inputs=[tau], drift=drift, input_matrix=input_matrix,
        input_weight=[[1]],
        parameters={symbols[k]: v for k, v in PARAMETERS.items()},
        input_low=-TORQUE_LIMIT, input_high=TORQUE_LIMIT,
        state_low=[-math.pi, -math.pi, -vb, -vb],
        state_high=[math.pi, math.pi, vb, vb],
        angle_dims=[0, 1], state_names=["theta1", "theta2", "theta1_dot", "theta2_dot"],
        input_names=["elbow_torque"],
        description="sparse_rrt two_link_acrobot (damped, |tau| <= 4), theta1 = 0 hanging"
                    + ("" if velocity_scale == 1.0 else
                       f"; velocity bounds x{velocity_scale:g}"),
        # the standard query with sparse_rrt's task-space goal region (velocities free): the
        # pipeline plans to it whenever the goal is this default one
        defaults={"start": list(START), "goal": list(GOAL), "goal_fn": task_goal_distance,
                  "goal_sampler": sample_task_goal,
                  "config": {"plan": {"goal_tolerance": TASK_GOAL_RADIUS,
                                      "time_limit": 60.0}}},
    )


def make_acrobot() -> SymbolicSystem:
    """sparse_rrt's acrobot with its stated bounds as the box and its swing-up query, to
    sparse_rrt's task-space goal region (`task_goal_distance`, `sample_task_goal`)."""
    return _make("sparse_rrt_acrobot", 1.0)


def make_acrobot_wide() -> SymbolicSystem:
    """The same with the velocity bounds widened by 50% (|theta1'|, |theta2'| <= 9)."""
    return _make("sparse_rrt_acrobot_wide", 1.5)


def end_effector(theta1, theta2):
    """sparse_rrt's task-space point of a state, (x, y) with L = 20 (numpy, broadcasting)."""
    t1 = np.asarray(theta1) - np.pi / 2
    t2 = np.asarray(theta2)
    return LINK_LENGTH_TASK * np.stack([np.cos(t1) + np.cos(t1 + t2),
                                        np.sin(t1) + np.sin(t1 + t2)], axis=-1)


_GOAL_POINT = end_effector(GOAL[0], GOAL[1])


def task_goal_distance(states) -> np.ndarray:
    """Distance (N,) of states (N, 4) to sparse_rrt's goal: the end effector's distance to the
    goal's; the goal is reached within `TASK_GOAL_RADIUS` (the plan's goal tolerance)."""
    states = np.atleast_2d(states)
    t1 = states[:, 0] - np.pi / 2
    t12 = t1 + states[:, 1]
    # (the planner asks this of every state it integrates: plain arithmetic, the goal's point
    # computed once)
    dx = LINK_LENGTH_TASK * (np.cos(t1) + np.cos(t12)) - _GOAL_POINT[0]
    dy = LINK_LENGTH_TASK * (np.sin(t1) + np.sin(t12)) - _GOAL_POINT[1]
    return np.sqrt(dx * dx + dy * dy)


def in_task_goal(states) -> np.ndarray:
    """sparse_rrt's goal test on states (N, 4): end effector within 2 of the goal's."""
    return task_goal_distance(states) <= TASK_GOAL_RADIUS


def sample_task_goal(rng: np.random.Generator) -> np.ndarray:
    """A state in sparse_rrt's goal region: angles near the goal's (rejection sampling over
    a box that holds the region's part near the upright), velocities uniform in their bounds."""
    for _ in range(1000):
        x = np.array([GOAL[0] + rng.uniform(-0.1, 0.1), GOAL[1] + rng.uniform(-0.2, 0.2),
                      rng.uniform(-VELOCITY_BOUND, VELOCITY_BOUND),
                      rng.uniform(-VELOCITY_BOUND, VELOCITY_BOUND)])
        if in_task_goal(x)[0]:
            return x
    return np.array(GOAL, dtype=float)


if __name__ == "__main__":
    from rrtcolearn.systems.check import check_system

    system = make_acrobot()
    check_system(system)
    print(f"{system.name}: check_system passed; run it with\n  rrtcolearn run --system "
          "examples.sparse_rrt_acrobot:make_acrobot")
