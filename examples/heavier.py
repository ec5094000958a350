"""The shipped systems with every mass and length 10% larger (inertias, mass x length^2,
x 1.1^3): the "true" systems a tracked plan is tested against
(`rrtcolearn track PLAN --true-system examples.heavier:cartpole`, bench/tracking_bench.py).
Gravity and the input boxes are the shipped ones."""

from __future__ import annotations

from rrtcolearn.systems.acrobot import make_acrobot
from rrtcolearn.systems.cartpole import make_cartpole
from rrtcolearn.systems.pendulum import make_pendulum
from rrtcolearn.systems.quadrotor import ARM, INERTIA, MASS, make_quadrotor

SCALE = 1.1


def pendulum():
    return make_pendulum({"m": SCALE, "l": SCALE})


def cartpole():
    return make_cartpole({"m_c": 10.0 * SCALE, "m_p": 1.0 * SCALE, "l": 0.5 * SCALE})


def acrobot():
    return make_acrobot({"m1": SCALE, "m2": SCALE, "l1": SCALE, "lc1": 0.5 * SCALE,
                         "lc2": 1.0 * SCALE, "Ic1": 0.083 * SCALE**3, "Ic2": 0.33 * SCALE**3})


def quadrotor():
    return make_quadrotor({"m": MASS * SCALE, "r": ARM * SCALE, "I": INERTIA * SCALE**3})
