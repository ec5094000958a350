"""dynobench interop (the optional extra ``dynobench``): read a benchmark problem as the
package ships it (environment YAML + robot model YAML), build the system and the planning
problem from it, and write plans in dynobench's result format.

A problem is named ``<robot>/<environment>`` (``unicycle1_v0/parallelpark_0``: the package's
``envs/unicycle1_v0/parallelpark_0.yaml``) or by the path of an environment file; its robot's
model is the package's ``models/<robot>.yaml``. The YAML is read here (pyyaml); the package's
compiled bindings (``pydynobench``: its own collision checker) are needed only to check
plans against it (`dynobench_distances`).

The systems are built through the public system API (`systems.symbolic.build_system`), each
as dynobench's C++ model states it: input-affine, with its input box and the model's body.
A system is named ``rrtcolearn.dynobench:<robot>`` so that a fitted run rebuilds it.
"""

from __future__ import annotations

import functools
import importlib.util
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rrtcolearn.errors import RRTCoLearnError
from rrtcolearn.geometry import Body, Box, Disc, Workspace

MODELS = ("unicycle1_v0", "unicycle2_v0", "quad2d_v0", "acrobot_v0", "integrator2_2d_v0")
"""The input-affine robot models of dynobench 0.0.4 this module reads."""
BUILT = MODELS
"""Those it builds systems for: all of them."""


class DynobenchError(RRTCoLearnError, ValueError):
    """A dynobench problem that cannot be read: one line naming the file and the key."""


def package_dir() -> Path:
    """The installed dynobench package's directory (not imported: its bindings print)."""
    spec = importlib.util.find_spec("dynobench")
    if spec is None or not spec.submodule_search_locations:
        raise DynobenchError("dynobench is not installed: pip install 'rrtcolearn[dynobench]'")
    return Path(next(iter(spec.submodule_search_locations)))


def shipped_problems(models: tuple[str, ...] = MODELS) -> list[str]:
    """Every ``<robot>/<environment>`` the package ships for ``models``."""
    envs = package_dir() / "envs"
    return [f"{m}/{p.stem}" for m in models for p in sorted((envs / m).glob("*.yaml"))]


def resolve(problem: str | Path) -> Path:
    """The environment file of ``problem``: a path, else ``<robot>/<env>`` in the package."""
    path = Path(problem)
    if path.suffix in (".yaml", ".yml") or path.is_file():
        if not path.is_file():
            raise DynobenchError(f"{path}: no such environment file")
        return path
    shipped = package_dir() / "envs" / f"{problem}.yaml"
    if not shipped.is_file():
        raise DynobenchError(f"{problem}: not a problem dynobench ships (e.g. "
                             "unicycle1_v0/parallelpark_0) nor an environment file")
    return shipped


@dataclass(frozen=True)
class DynobenchProblem:
    """One dynobench problem as read: the environment's box, obstacles (workspace shapes),
    the robot's type, start and goal, and its model's parameters."""

    name: str
    path: Path
    robot: str
    model: dict[str, Any]
    low: np.ndarray
    high: np.ndarray
    obstacles: tuple[Box | Disc, ...]
    start: np.ndarray
    goal: np.ndarray

    @property
    def dt(self) -> float:
        """dynobench's time grid of this robot (its model's ``dt``, else its C++ default)."""
        return float(self.model["dt"])


def _yaml(path: Path) -> dict:
    import yaml

    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise DynobenchError(f"{path}: cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        line = str(exc).replace("\n", " ")
        raise DynobenchError(f"{path}: not valid YAML ({line})") from None
    if not isinstance(data, dict):
        raise DynobenchError(f"{path}: expected a mapping of keys, got {type(data).__name__}")
    return data


def _numbers(path: Path, key: str, value, length: int | None = None) -> np.ndarray:
    ok = isinstance(value, list) and all(isinstance(v, int | float) and not isinstance(v, bool)
                                         for v in value)
    a = np.asarray(value, dtype=np.float64) if ok else None
    if a is None or (length is not None and a.size != length) or not np.all(np.isfinite(a)):
        want = f"{length} " if length is not None else ""
        raise DynobenchError(f"{path}: {key}: expected a list of {want}finite numbers, got "
                             f"{value!r}")
    return a


_STATES = {"unicycle1_v0": 3, "unicycle2_v0": 5, "quad2d_v0": 6, "acrobot_v0": 4,
           "integrator2_2d_v0": 4}


def read_problem(problem: str | Path, models: Path | None = None) -> DynobenchProblem:
    """Read ``problem`` (`resolve`) and its robot's model (``models``: a directory of model
    files, default the package's); DynobenchError naming the file and key otherwise."""
    path = resolve(problem)
    data = _yaml(path)
    env = data.get("environment")
    if not isinstance(env, dict):
        raise DynobenchError(f"{path}: environment: expected a mapping with min, max, "
                             "obstacles")
    low = _numbers(path, "environment.min", env.get("min"))
    high = _numbers(path, "environment.max", env.get("max"), low.size)
    if low.size not in (2, 3) or np.any(low >= high):
        raise DynobenchError(f"{path}: environment.min/max: expected 2 or 3 values with min "
                             f"< max, got {env.get('min')!r}, {env.get('max')!r}")
    obstacles = []
    for k, ob in enumerate(env.get("obstacles") or []):
        key = f"environment.obstacles[{k}]"
        if not isinstance(ob, dict) or ob.get("type") not in ("box", "sphere"):
            raise DynobenchError(f"{path}: {key}.type: expected box or sphere, got "
                                 f"{ob.get('type') if isinstance(ob, dict) else ob!r}")
        center = _numbers(path, f"{key}.center", ob.get("center"), low.size)
        if ob["type"] == "box":
            size = _numbers(path, f"{key}.size", ob.get("size"), low.size)
            if np.any(size <= 0):
                raise DynobenchError(f"{path}: {key}.size: must be positive, got {ob['size']}")
            obstacles.append(Box(center, size))
        else:
            radius = ob.get("size", ob.get("radius"))
            radius = radius[0] if isinstance(radius, list) and len(radius) == 1 else radius
            if not isinstance(radius, int | float) or radius <= 0:
                raise DynobenchError(f"{path}: {key}.size: expected a radius, got {radius!r}")
            obstacles.append(Disc(center, float(radius)))
    robots = data.get("robots")
    if not isinstance(robots, list) or len(robots) != 1 or not isinstance(robots[0], dict):
        raise DynobenchError(f"{path}: robots: expected one robot, got {robots!r}")
    robot = robots[0].get("type")
    if robot not in _STATES:
        raise DynobenchError(f"{path}: robots[0].type: {robot!r} is not an input-affine model "
                             f"read here ({', '.join(MODELS)})")
    n = _STATES[robot]
    start = _numbers(path, "robots[0].start", robots[0].get("start"), n)
    goal = _numbers(path, "robots[0].goal", robots[0].get("goal"), n)
    model_path = (models or package_dir() / "models") / f"{robot}.yaml"
    if not model_path.is_file():
        raise DynobenchError(f"{path}: robots[0].type: no model file {model_path}")
    model = _read_model(model_path, robot)
    name = f"{robot}/{path.stem}" if path.parent.name == robot else str(path)
    return DynobenchProblem(name, path, robot, model, low, high, tuple(obstacles), start,
                            goal)


def _read_model(path: Path, robot: str) -> dict[str, Any]:
    """The model file's parameters over dynobench's defaults, those the system reads checked
    as numbers; DynobenchError naming the file and key."""
    model = {**_DEFAULTS[robot], **_yaml(path)}
    for key in _MODEL_KEYS[robot]:
        value = model.get(key)
        if isinstance(value, str):  # YAML 1.1 reads 1e-4 as text; dynobench's C++ as a number
            try:
                value = model[key] = float(value)
            except ValueError:
                pass
        if key == "size":
            _numbers(path, key, value, 2)
        elif not isinstance(value, int | float) or isinstance(value, bool) \
                or not math.isfinite(value):
            raise DynobenchError(f"{path}: {key}: expected a number, got {value!r}")
    return model


# the parameters each built system reads (checked as numbers) ...
_MODEL_KEYS = {
    "unicycle1_v0": ("max_vel", "min_vel", "max_angular_vel", "min_angular_vel", "size",
                     "dt"),
    "unicycle2_v0": ("max_vel", "min_vel", "max_angular_vel", "min_angular_vel",
                     "max_acc_abs", "max_angular_acc", "size", "dt"),
    "quad2d_v0": ("max_f", "m", "I", "l", "max_vel", "max_angular_vel", "size", "dt"),
    "acrobot_v0": ("l1", "l2", "lc1", "lc2", "m1", "m2", "I1", "I2", "max_torque",
                   "max_angular_vel", "dt"),
    "integrator2_2d_v0": ("max_vel", "max_acc", "size", "dt"),
}
# ... and, where the model file leaves one out, its default in dynobench's C++ parameter
# structs (include/dynobench/<model>.hpp: Quad2d_params, Acrobot_params,
# Integrator2_2d_params; unicycle1.hpp, unicycle2.hpp): integrator2_2d_v0.yaml states none
_DEFAULTS = {
    "unicycle1_v0": {"dt": 0.1},
    "unicycle2_v0": {"dt": 0.1},
    "quad2d_v0": {"dt": 0.01, "drag_against_vel": False},
    "acrobot_v0": {"dt": 0.01},
    "integrator2_2d_v0": {"dt": 0.1, "max_vel": 1.0, "max_acc": 1.0, "size": [0.5, 0.25],
                          "shape": "box"},
}
G = 9.81
"""Gravity as dynobench's C++ models state it (Model_quad2d::g, Model_acrobot::g)."""


def body(problem: DynobenchProblem) -> Body:
    """The robot's body as dynobench collides it (the model's ``collision_geometries`` and
    ``transformation_collision_geometries``): a box of the model's ``size`` at (x, y,
    heading) for the unicycles and quad2d, at (x, y) unturned for the double integrator;
    the acrobot's two links as boxes l1 x 0.1 and l2 x 0.1 along the links (`acrobot_links`)."""
    if problem.model.get("shape", "box") != "box":
        raise DynobenchError(f"{problem.path}: shape: only box bodies are read")
    if problem.robot == "acrobot_v0":
        m = problem.model
        return Body((Box(np.array([m["lc1"], 0.0]), np.array([m["l1"], _LINK_WIDTH])),
                     Box(np.array([m["lc2"], 0.0]), np.array([m["l2"], _LINK_WIDTH]))),
                    fk="rrtcolearn.dynobench:acrobot_links")
    pose = (0, 1) if problem.robot == "integrator2_2d_v0" else (0, 1, 2)
    return Body((Box(np.zeros(2), np.asarray(problem.model["size"], dtype=float)),), pose)


_LINK_WIDTH = 0.1  # Model_acrobot: `const double width = .1` (not a model parameter)


def acrobot_links(states: np.ndarray) -> np.ndarray:
    """Forward kinematics of dynobench's acrobot (src/acrobot.cpp,
    ``transformation_collision_geometries``): states (N, 4) -> the poses (N, 2, 3) of its
    two links' pivots, heading along the link. Angles are offset by 3 pi / 2: q1 = 0 hangs
    straight down from the pivot at the origin; link 2 turns by q1 + q2 from the elbow."""
    x = np.atleast_2d(states)
    l1 = _acrobot_parameters()["l1"]
    a1 = x[:, 0] + 1.5 * np.pi
    a2 = a1 + x[:, 1]
    out = np.zeros((len(x), 2, 3))
    out[:, 0, 2] = a1
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = l1 * np.cos(a1), l1 * np.sin(a1), a2
    return out


@functools.cache
def _acrobot_parameters() -> dict:
    return _model("acrobot_v0")


def workspace(problem: DynobenchProblem) -> Workspace:
    """The body among the problem's obstacles: the planner's exact collision test."""
    return Workspace(body(problem), problem.obstacles)


# the data's sampling box in x, y: every shipped environment of the robot (the learned
# model is not translation invariant, so it sees the region any of them plans in)
def _position_box(robot: str) -> tuple[list[float], list[float]]:
    lows, highs = [], []
    for name in shipped_problems((robot,)):
        p = read_problem(name)
        lows.append(p.low)
        highs.append(p.high)
    return np.min(lows, axis=0).tolist(), np.max(highs, axis=0).tolist()


def _model(robot: str) -> dict:
    return _read_model(package_dir() / "models" / f"{robot}.yaml", robot)


def _common(robot: str, angle_dims: list[int]) -> dict:
    return {"angle_dims": angle_dims, "description": f"dynobench {robot}",
            "defaults": {"config": _RECOMMENDED[robot]}}


def _unicycle(robot: str):
    import sympy

    from rrtcolearn.systems.symbolic import build_system
    model = _model(robot)
    lo, hi = _position_box(robot)
    x, y, th = sympy.symbols("x y theta", real=True)
    if robot == "unicycle1_v0":
        v, w = sympy.symbols("v omega", real=True)
        return build_system(
            f"rrtcolearn.dynobench:{robot}", [x, y, th], [v, w],
            drift=[0, 0, 0], input_matrix=[[sympy.cos(th), 0], [sympy.sin(th), 0], [0, 1]],
            input_low=[model["min_vel"], model["min_angular_vel"]],
            input_high=[model["max_vel"], model["max_angular_vel"]],
            state_low=[*lo, -math.pi], state_high=[*hi, math.pi], **_common(robot, [2]))
    v, w, a, al = sympy.symbols("v omega a alpha", real=True)
    return build_system(
        f"rrtcolearn.dynobench:{robot}", [x, y, th, v, w], [a, al],
        drift=[v * sympy.cos(th), v * sympy.sin(th), w, 0, 0],
        input_matrix=[[0, 0], [0, 0], [0, 0], [1, 0], [0, 1]],
        input_low=[-model["max_acc_abs"], -model["max_angular_acc"]],
        input_high=[model["max_acc_abs"], model["max_angular_acc"]],
        state_low=[*lo, -math.pi, model["min_vel"], model["min_angular_vel"]],
        state_high=[*hi, math.pi, model["max_vel"], model["max_angular_vel"]],
        **_common(robot, [2]))


# The time weight w of each robot: dynobench minimises duration, and the running cost is
# w + u^T u / 2; w = 4 max(u^T u / 2) over the input box makes time at least 80% of it at
# the input limits (the unicycles: 1; quad2d: f <= 1.3, 4 x 1.69 = 6.76; the acrobot:
# |u| <= 10, 200; the double integrator: |a| <= 1, 4) while the data stay those of a
# smooth optimal control problem. The simulations: the derived count for the first-order
# unicycle (63 000), 30 000 for the others (the derived count grows by 2.5 per pair of
# states: 390 000 for quad2d's six), so each model's offline CPU stays well under 10 min.
_RECOMMENDED = {
    "unicycle1_v0": {"system": {"time_weight": 1.0}},
    "unicycle2_v0": {"system": {"time_weight": 1.0}, "generate": {"n_simulations": 30000}},
    "quad2d_v0": {"system": {"time_weight": 6.76}, "generate": {"n_simulations": 30000}},
    "acrobot_v0": {"system": {"time_weight": 200.0}, "generate": {"n_simulations": 30000}},
    "integrator2_2d_v0": {"system": {"time_weight": 4.0},
                          "generate": {"n_simulations": 30000}},
}


def unicycle1_v0():
    """dynobench's first-order unicycle: x' = v cos(theta), y' = v sin(theta), theta' = omega,
    |v|, |omega| <= 0.5."""
    return _unicycle("unicycle1_v0")


def unicycle2_v0():
    """dynobench's second-order unicycle: v' = a, omega' = alpha, |a|, |alpha| <= 0.25 and
    |v|, |omega| <= 0.5 as state constraints."""
    return _unicycle("unicycle2_v0")


def quad2d_v0():
    """dynobench's planar quadrotor (src/planar_rotor.cpp, ``Model_quad2d::calcV``): state
    (x, y, yaw, x', y', yaw'), inputs the two rotors' thrusts f1, f2 in [0, max_f] in units
    of the hover thrust m g / 2: x'' = -(f1 + f2) (m g / 2) sin(yaw) / m, y'' = (f1 + f2)
    (m g / 2) cos(yaw) / m - g, yaw'' = l (f1 - f2) (m g / 2) / I; |x'|, |y'| <= max_vel,
    |yaw'| <= max_angular_vel (its x_lb, x_ub). No drag (the model's drag_against_vel is
    false)."""
    import sympy

    from rrtcolearn.systems.symbolic import build_system
    robot = "quad2d_v0"
    m = _model(robot)
    if m["drag_against_vel"]:
        raise DynobenchError(f"{package_dir() / 'models' / 'quad2d_v0.yaml'}: "
                             "drag_against_vel: drag is not built")
    lo, hi = _position_box(robot)
    x, y, th, vx, vy, w = sympy.symbols("x y yaw vx vy omega", real=True)
    f1, f2 = sympy.symbols("f1 f2", real=True)
    k = sympy.Float(m["m"]) * G / 2  # u_nominal: the thrust in newtons per unit input
    c, s = sympy.cos(th), sympy.sin(th)
    acc = k / m["m"]
    turn = m["l"] * k / m["I"]
    return build_system(
        f"rrtcolearn.dynobench:{robot}", [x, y, th, vx, vy, w], [f1, f2],
        drift=[vx, vy, w, 0, -G, 0],
        input_matrix=[[0, 0], [0, 0], [0, 0], [-acc * s, -acc * s], [acc * c, acc * c],
                      [turn, -turn]],
        input_low=[0.0, 0.0], input_high=[m["max_f"], m["max_f"]],
        state_low=[*lo, -math.pi, -m["max_vel"], -m["max_vel"], -m["max_angular_vel"]],
        state_high=[*hi, math.pi, m["max_vel"], m["max_vel"], m["max_angular_vel"]],
        **_common(robot, [2]))


def acrobot_v0():
    """dynobench's acrobot (src/acrobot.cpp, ``Model_acrobot::calcV``, transcribed): state
    (q1, q2, q1', q2'), q1 = 0 hanging down, q2 the elbow relative to link 1, the torque u at
    the elbow, |u| <= max_torque, |q1'|, |q2'| <= max_angular_vel; I1, I2 about the pivots."""
    import sympy

    from rrtcolearn.systems.symbolic import build_system
    robot = "acrobot_v0"
    p = _model(robot)
    q1, q2, d1, d2, u = sympy.symbols("q1 q2 q1dot q2dot u", real=True)
    m1, m2, l1, lc1, lc2, i1, i2 = (sympy.Float(p[k]) for k in
                                    ("m1", "m2", "l1", "lc1", "lc2", "I1", "I2"))
    g = sympy.Float(G)
    a = (g * lc1 * m1 * sympy.sin(q1) + g * m2 * (l1 * sympy.sin(q1) + lc2 * sympy.sin(q1 + q2))
         - 2 * l1 * lc2 * m2 * d1 * d2 * sympy.sin(q2) - l1 * lc2 * m2 * d2**2 * sympy.sin(q2))
    b = g * lc2 * m2 * sympy.sin(q1 + q2) + l1 * lc2 * m2 * d1**2 * sympy.sin(q2) - u
    det = i1 * i2 + i2 * l1**2 * m2 - l1**2 * lc2**2 * m2**2 * sympy.cos(q2)**2
    q1dd = (-i2 * a + (i2 + l1 * lc2 * m2 * sympy.cos(q2)) * b) / det
    q2dd = ((i2 + l1 * lc2 * m2 * sympy.cos(q2)) * a
            - b * (i1 + i2 + l1**2 * m2 + 2 * l1 * lc2 * m2 * sympy.cos(q2))) / det
    # input-affine: the drift at u = 0 and the input column d/du (both exact: linear in u)
    drift = [d1, d2, q1dd.subs(u, 0), q2dd.subs(u, 0)]
    column = [0, 0, sympy.diff(q1dd, u), sympy.diff(q2dd, u)]
    vmax = p["max_angular_vel"]
    return build_system(
        f"rrtcolearn.dynobench:{robot}", [q1, q2, d1, d2], [u], drift=drift,
        input_matrix=[[e] for e in column], input_low=[-p["max_torque"]],
        input_high=[p["max_torque"]], state_low=[-math.pi, -math.pi, -vmax, -vmax],
        state_high=[math.pi, math.pi, vmax, vmax], **_common(robot, [0, 1]))


def integrator2_2d_v0():
    """dynobench's 2-D double integrator (src/integrator2_2d.cpp, ``calcV``): state (x, y,
    vx, vy), inputs the accelerations, |a| <= max_acc, |v| <= max_vel (defaults 1, 1:
    Integrator2_2d_params; the model file states none)."""
    import sympy

    from rrtcolearn.systems.symbolic import build_system
    robot = "integrator2_2d_v0"
    m = _model(robot)
    lo, hi = _position_box(robot)
    x, y, vx, vy, ax, ay = sympy.symbols("x y vx vy ax ay", real=True)
    return build_system(
        f"rrtcolearn.dynobench:{robot}", [x, y, vx, vy], [ax, ay], drift=[vx, vy, 0, 0],
        input_matrix=[[0, 0], [0, 0], [1, 0], [0, 1]],
        input_low=[-m["max_acc"]] * 2, input_high=[m["max_acc"]] * 2,
        state_low=[*lo, -m["max_vel"], -m["max_vel"]],
        state_high=[*hi, m["max_vel"], m["max_vel"]], **_common(robot, []))


def make_system(problem: DynobenchProblem):
    """The rrtcolearn system of the problem's robot."""
    if problem.robot not in BUILT:
        raise DynobenchError(f"{problem.path}: robots[0].type: {problem.robot} is read but "
                             f"not built yet (built: {', '.join(BUILT)})")
    from rrtcolearn.systems import make
    return make(system_name(problem.robot))


def system_name(robot: str) -> str:
    return f"rrtcolearn.dynobench:{robot}"


def planning_problem(problem: DynobenchProblem, system, goal_tolerance: float = 0.1, *,
                     inflated: bool = False):
    """The `PlanningProblem` of ``problem`` on ``system`` (`config_options`' query): the
    environment's box as state constraints on x, y (and the velocities as the model bounds
    them), the exact body among the obstacles (``inflated``: the point among grown boxes,
    the comparison row)."""
    from rrtcolearn.planning.problem import PlanningProblem
    plan = config_options(problem)["plan"]
    ws = workspace(problem)
    return PlanningProblem.create(
        system, plan["start"], plan["goal"], goal_tolerance,
        obstacles=[ws.inflated() if inflated else ws], state_low=plan["state_low"],
        state_high=plan["state_high"], wrap_goal=True)


def result(problem: DynobenchProblem, samples: dict[str, np.ndarray]) -> dict[str, Any]:
    """A plan's path in dynobench's result format: ``states`` (K + 1) and ``actions`` (K) on
    its time grid dt, from ``samples`` (`evaluate.sample_path` at the plan's step): the
    state at each t = k dt and the mean input over [t, t + dt) (held over the step, as
    dynobench's models integrate); a path whose duration is no whole number of steps ends
    with a shorter step to its end state, whose length ``times`` records."""
    t, x, u = samples["t"], samples["state"], samples["input"]
    dt, duration = problem.dt, float(t[-1])
    k = int(np.floor(duration / dt + 1e-9))
    grid = [i * dt for i in range(k + 1)]
    if duration - grid[-1] > 1e-9:
        grid.append(duration)
    idx = [int(np.argmin(np.abs(t - g))) for g in grid]
    actions = [u[a:b].mean(axis=0) if b > a else u[a] for a, b in itertools.pairwise(idx)]
    return {"feasible": 1, "cost": duration, "start": problem.start.tolist(),
            "goal": problem.goal.tolist(), "num_states": len(idx),
            "states": [x[i].tolist() for i in idx], "num_actions": len(actions),
            "actions": [np.asarray(a).tolist() for a in actions], "times": grid}


def write_result(path: str | Path, content: dict[str, Any]) -> None:
    """Write a result (`result`) as dynobench's YAML."""
    import yaml

    Path(path).write_text(yaml.safe_dump(content, default_flow_style=None, sort_keys=False),
                          encoding="utf-8")


def references(problem: DynobenchProblem) -> dict[str, dict[str, float]]:
    """The reference solutions the package ships beside the environment (``<env>/*.yaml``):
    {planner: {cost (s, the path duration), time_stamp (as shipped: the time to that
    solution on the authors' machine)}}, feasible ones only."""
    out = {}
    for f in sorted((problem.path.parent / problem.path.stem).glob("*solution*.yaml")):
        d = _yaml(f)
        if d.get("feasible") == 1:
            stamp = float(d["time_stamp"])
            # the rrt_to files ship an uninitialised time stamp (e.g. 1.8e-316): none there
            out[f.stem] = {"cost": float(d["cost"]),
                           "time_stamp": stamp if stamp > 1e-6 else float("nan")}
    return out


def dynobench_model(problem: DynobenchProblem):
    """dynobench's own model of the problem's robot in its environment (its compiled
    bindings: ``calcV``, ``collision_distance``, bounds). The bindings print while loading;
    that output is silenced here."""
    import os

    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            import dynobench

            return dynobench.robot_factory_with_env(
                str(package_dir() / "models" / f"{problem.robot}.yaml"), str(problem.path))
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def dynobench_distances(problem: DynobenchProblem, states: np.ndarray) -> np.ndarray:
    """dynobench's own collision checker (its bindings, fcl, the model's body) on every
    state: the signed distance to the nearest obstacle (<= 0: in collision)."""
    import dynobench

    robot = dynobench_model(problem)
    out = dynobench.CollisionOut()
    dist = np.empty(len(states))
    for i, x in enumerate(np.asarray(states, dtype=np.float64)):
        robot.collision_distance(x, out)
        dist[i] = out.distance
    return dist


def config_options(problem: DynobenchProblem) -> dict[str, dict[str, Any]]:
    """The configuration sections that pose ``problem`` (nested as in a file): its robot's
    system, and the plan's query, state constraints, body and obstacles, so that a run
    records them and its figure draws them."""
    system = make_system(problem)
    # the system's box bounds the angles (a turn) and the velocities as dynobench's x_lb,
    # x_ub do; the environment's box bounds the position (the acrobot has none: fixed base)
    low, high = system.state_low.tolist(), system.state_high.tolist()
    if problem.robot != "acrobot_v0":
        low[:2], high[:2] = problem.low[:2].tolist(), problem.high[:2].tolist()
    # angles in [-pi, pi), as dynobench's `ensure` wraps them (the acrobot's goal is
    # 3.141593, past pi)
    start, goal = problem.start.copy(), problem.goal.copy()
    for j in system.angle_dims:
        start[j], goal[j] = (np.mod(np.array([start[j], goal[j]]) + np.pi, 2 * np.pi) - np.pi)
    return {"system": {"name": system_name(problem.robot)},
            "plan": {"start": start.tolist(), "goal": goal.tolist(),
                     "state_low": low, "state_high": high, "wrap_goal": True,
                     "obstacles": [o.to_dict() for o in problem.obstacles],
                     "body": body(problem).to_dict()}}
