"""dynobench interop (rrtcolearn.dynobench): the reader on every problem the package ships,
one-line errors naming the file and key, the exact body against dynobench's own collision
checker (its compiled bindings: fcl), and plans exported in its result format."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from tests import references as ref

from rrtcolearn import dynobench as db
from rrtcolearn.planning.termination import TerminationCondition

SHIPPED = db.shipped_problems()


def test_every_shipped_problem_of_the_input_affine_models_is_found():
    per_model = {m: sum(p.startswith(m + "/") for p in SHIPPED) for m in db.MODELS}
    # counted by hand in dynobench 0.0.4's envs/
    assert per_model == {"unicycle1_v0": 3, "unicycle2_v0": 3, "quad2d_v0": 7,
                         "acrobot_v0": 5, "integrator2_2d_v0": 2}


@pytest.mark.parametrize("name", SHIPPED)
def test_the_reader_on_every_shipped_problem(name):
    p = db.read_problem(name)
    raw = yaml.safe_load((db.package_dir() / "envs" / f"{name}.yaml").read_text())
    env, robot = raw["environment"], raw["robots"][0]
    assert p.name == name and p.robot == robot["type"] == name.split("/")[0]
    assert p.low.tolist() == env["min"] and p.high.tolist() == env["max"]
    assert p.start.tolist() == robot["start"] and p.goal.tolist() == robot["goal"]
    obs = env.get("obstacles") or []
    assert len(p.obstacles) == len(obs)
    for mine, theirs in zip(p.obstacles, obs, strict=True):
        assert mine.center.tolist() == theirs["center"] and mine.size.tolist() == theirs["size"]
    model = yaml.safe_load((db.package_dir() / "models" / f"{p.robot}.yaml").read_text())
    # the C++ parameter structs' defaults where the model file states no dt (acrobot.hpp:
    # 0.01, integrator2_2d.hpp: 0.1); the shipped references are on that grid
    assert p.dt == model.get("dt", {"acrobot_v0": 0.01}.get(p.robot, 0.1))
    for shipped in sorted((p.path.parent / p.path.stem).glob("*_solution_v0.yaml")):
        sol = yaml.safe_load(shipped.read_text())
        if sol.get("feasible") == 1:
            assert len(sol["states"]) - 1 == pytest.approx(sol["cost"] / p.dt, abs=1.01)
    # every shipped problem poses a planning problem: start and goal in the box, clear
    problem = db.planning_problem(p, db.make_system(p))
    assert problem.validity(np.stack([problem.start, problem.goal])).all()


GOOD = """name: t
environment:
  min: [0, 0]
  max: [3, 1.2]
  obstacles:
    - type: box
      center: [0.3, 0.3]
      size: [0.5, 0.25]
robots:
  - type: unicycle1_v0
    start: [0.7, 0.8, 0]
    goal: [1.9, 0.3, 0]
"""


@pytest.mark.parametrize("old, new, key", [
    ("environment:", "environmnt:", "environment"),
    ("min: [0, 0]", "min: [0, a]", "environment.min"),
    ("max: [3, 1.2]", "max: [3]", "environment.max"),
    ("center: [0.3, 0.3]", "center: [0.3]", "environment.obstacles[0].center"),
    ("type: box", "type: mesh", "environment.obstacles[0].type"),
    ("size: [0.5, 0.25]", "size: [0.5, -1]", "environment.obstacles[0].size"),
    ("type: unicycle1_v0", "type: car1_v0", "robots[0].type"),
    ("start: [0.7, 0.8, 0]", "start: [0.7, 0.8]", "robots[0].start"),
    ("goal: [1.9, 0.3, 0]", "goal: [1.9, 0.3, .nan]", "robots[0].goal"),
    ("robots:", "robotz:", "robots"),
])
def test_bad_environment_files_get_one_line_naming_file_and_key(tmp_path, old, new, key):
    path = tmp_path / "env.yaml"
    assert old in GOOD
    path.write_text(GOOD.replace(old, new))
    with pytest.raises(db.DynobenchError) as info:
        db.read_problem(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: {key}:") and "\n" not in msg


@pytest.mark.parametrize("robot, key, bad", [
    ("quad2d_v0", "I", "heavy"), ("quad2d_v0", "size", "[.6]"), ("acrobot_v0", "l1", ".nan"),
    ("acrobot_v0", "max_torque", "[10]"), ("integrator2_2d_v0", "max_acc", "fast")])
def test_bad_model_files_of_the_other_robots_name_file_and_key(tmp_path, robot, key, bad):
    env = tmp_path / "env.yaml"
    raw = yaml.safe_load((db.package_dir() / "envs" / f"{FIRST[robot]}.yaml").read_text())
    env.write_text(yaml.safe_dump(raw))
    models = tmp_path / "models"
    models.mkdir()
    text = (db.package_dir() / "models" / f"{robot}.yaml").read_text()
    (models / f"{robot}.yaml").write_text(text + f"\n{key}: {bad}\n")
    with pytest.raises(db.DynobenchError) as info:
        db.read_problem(env, models)
    msg = str(info.value)
    assert msg.startswith(f"{models / (robot + '.yaml')}: {key}:") and "\n" not in msg


def test_bad_yaml_and_bad_model_files(tmp_path):
    path = tmp_path / "env.yaml"
    path.write_text("environment: [\n")
    with pytest.raises(db.DynobenchError, match=rf"^{path}: not valid YAML"):
        db.read_problem(path)
    path.write_text(GOOD)
    models = tmp_path / "models"
    models.mkdir()
    text = (db.package_dir() / "models" / "unicycle1_v0.yaml").read_text()
    (models / "unicycle1_v0.yaml").write_text(text.replace("max_vel: 0.5", "max_vel: fast"))
    with pytest.raises(db.DynobenchError, match=rf"^{models / 'unicycle1_v0.yaml'}: max_vel:"):
        db.read_problem(path, models)
    with pytest.raises(db.DynobenchError, match=r"^nowhere/x: not a problem"):
        db.read_problem("nowhere/x")


def _body_polygons(robot, x):
    """The body's corners written out from dynobench's C++ (collision_geometries and
    transformation_collision_geometries of each model)."""
    from test_geometry import corners
    if robot == "acrobot_v0":  # links 1 x 0.1 centred lc = 0.5 along each, 3 pi / 2 offset
        a1, a2 = x[0] + 1.5 * np.pi, x[0] + x[1] + 1.5 * np.pi
        elbow = np.array([np.cos(a1), np.sin(a1)])
        c2 = elbow + 0.5 * np.array([np.cos(a2), np.sin(a2)])
        return [corners(0.5 * np.cos(a1), 0.5 * np.sin(a1), 1.0, 0.1, a1),
                corners(*c2, 1.0, 0.1, a2)]
    size = {"quad2d_v0": (0.6, 0.2)}.get(robot, (0.5, 0.25))  # the model files' size
    return [corners(x[0], x[1], *size, 0.0 if robot == "integrator2_2d_v0" else x[2])]


@pytest.mark.parametrize("name", ["unicycle1_v0/parallelpark_0", "unicycle1_v0/kink_0",
                                  "unicycle1_v0/bugtrap_0", "quad2d_v0/quad_obs_column",
                                  "quad2d_v0/quad_bugtrap", "acrobot_v0/swing_up_obs_hard",
                                  "integrator2_2d_v0/park"])
def test_the_exact_body_agrees_with_dynobenchs_checker_and_a_polygon_test(name):
    # dynobench's checker (fcl) is asked only where the exact test finds the body free: its
    # penetration query on a body deep in an obstacle can run for minutes (e.g.
    # [2.324, 0.211, -1.42] on parallelpark_0); where the body collides the reference is the
    # brute-force polygon test of test_geometry (segment crossings, point in polygon) on
    # the body written out by hand
    from test_geometry import corners, polys_meet
    p = db.read_problem(name)
    system = db.make_system(p)
    rng = np.random.default_rng(7)
    x = rng.uniform(system.state_low, system.state_high, (1500, system.n_states))
    if p.robot != "acrobot_v0":
        x[:, :2] = rng.uniform(p.low, p.high, (1500, 2))
    mine = db.workspace(p).contains(x)
    assert 40 < mine.sum() < 1450
    theirs = db.dynobench_distances(p, x[~mine])
    assert np.all(theirs > -1e-5)  # fcl's geometry is in single precision
    obstacles = [corners(*o.center, *o.size, 0.0) for o in p.obstacles]
    for xi in x[mine]:
        assert any(polys_meet(b, o) for b in _body_polygons(p.robot, xi) for o in obstacles)
    for xi in x[~mine][:200]:
        assert not any(polys_meet(b, o) for b in _body_polygons(p.robot, xi)
                       for o in obstacles)


def test_a_body_of_links_is_written_and_read_by_its_functions_name():
    from rrtcolearn.geometry import Workspace
    p = db.read_problem("acrobot_v0/swing_up_obs")
    ws = db.workspace(p)
    again = Workspace.from_dict(yaml.safe_load(yaml.safe_dump(ws.to_dict())))
    x = np.random.default_rng(2).uniform(-np.pi, np.pi, (500, 4))
    assert again.body.fk == "rrtcolearn.dynobench:acrobot_links"
    assert np.array_equal(again.contains(x), ws.contains(x)) and ws.contains(x).any()
    spec = ws.to_dict()
    spec["body"]["fk"] = "rrtcolearn.dynobench:no_such_function"
    with pytest.raises(ValueError, match=r"^fk: cannot find 'rrtcolearn\.dynobench:no_such"):
        Workspace.from_dict(spec)
    spec["body"]["fk"] = "a function"
    with pytest.raises(ValueError, match=r"^fk: a body placed by forward kinematics"):
        Workspace.from_dict(spec)


def test_a_plan_exported_in_dynobenchs_format_passes_its_checker(tmp_path):
    from rrtcolearn import planners
    from rrtcolearn.evaluate import sample_path
    p = db.read_problem("unicycle1_v0/parallelpark_0")
    system = db.make_system(p)
    prob = db.planning_problem(p, system, goal_tolerance=0.1)
    plan = planners.make("random-rrt").solve(
        prob, TerminationCondition(time_limit=None, max_iterations=20000), seed=0)
    assert plan.solved
    samples = sample_path(system, plan)
    out = tmp_path / "result.yaml"
    db.write_result(out, db.result(p, samples))
    res = yaml.safe_load(out.read_text())
    states, actions, times = (np.array(res[k]) for k in ("states", "actions", "times"))
    assert res["num_states"] == len(states) == len(actions) + 1 == len(times)
    assert np.allclose(np.diff(times)[:-1], 0.1) and 0 < np.diff(times)[-1] <= 0.1 + 1e-9
    assert times[-1] == pytest.approx(plan.path_duration)
    assert np.allclose(states[0], p.start) and np.all(np.abs(actions) <= 0.5 + 1e-12)
    assert np.linalg.norm(states[-1, :2] - p.goal[:2]) <= 0.1
    # dynobench's own checker: every exported state and every step the planner checked
    assert np.all(db.dynobench_distances(p, states) > 0)
    assert np.all(db.dynobench_distances(p, samples["state"]) > 0)


def test_references_are_the_shipped_feasible_solutions():
    p = db.read_problem("unicycle1_v0/parallelpark_0")
    refs = db.references(p)
    assert refs["idbastar_v0_solution_v0"] == {"cost": 3.1, "time_stamp": 1121.1}
    assert np.isnan(refs["rrt_to_v0_solution_v0"]["time_stamp"])  # shipped uninitialised
    assert "idbastar_v0_db_solution_v0" not in refs  # feasible: 0
    # a shipped solution's states are clear of the obstacles by the exact test too
    sol = yaml.safe_load(Path(p.path.parent / p.path.stem / "idbastar_v0_solution_v0.yaml")
                         .read_text())
    assert not db.workspace(p).contains(np.array(sol["states"])).any()


FIRST = {m: next(p for p in SHIPPED if p.startswith(m + "/")) for m in db.MODELS}
REFERENCES = {"quad2d_v0": ref.dynobench_quad2d, "acrobot_v0": ref.dynobench_acrobot,
              "integrator2_2d_v0": ref.double_integrator_2d}


def _samples(system, n=300, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = system.input_limits()
    return (rng.uniform(system.state_low, system.state_high, (n, system.n_states)),
            rng.uniform(lo, hi, (n, system.n_inputs)))


@pytest.mark.parametrize("robot", sorted(REFERENCES))
def test_the_built_systems_against_hand_written_references(robot):
    # tests/references.py: Tedrake's manipulator equations solved numerically (the package
    # transcribes dynobench's closed form), dynobench's parameters written out by hand
    system = db.make_system(db.read_problem(FIRST[robot]))
    x, u = _samples(system)
    assert np.allclose(system.dynamics(x, u), REFERENCES[robot](x, u), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("robot", db.MODELS)
def test_the_built_systems_against_dynobenchs_own_model(robot):
    # its compiled calcV, input box and velocity bounds (x_lb, x_ub beyond the position)
    p = db.read_problem(FIRST[robot])
    system, theirs = db.make_system(p), db.dynobench_model(p)
    x, u = _samples(system, seed=1)
    v = np.zeros(system.n_states)
    for xi, ui, fi in zip(x, u, system.dynamics(x, u), strict=True):
        theirs.calcV(v, xi, ui)
        assert np.allclose(fi, v, rtol=1e-12, atol=1e-12)
    lo, hi = system.input_limits()
    assert np.array_equal(lo, theirs.get_u_lb()) and np.array_equal(hi, theirs.get_u_ub())
    first = 0 if robot == "acrobot_v0" else 2  # velocities (and turn rates) after the pose
    bounded = [j for j in range(first, system.n_states) if j not in system.angle_dims]
    assert np.array_equal(system.state_low[bounded], theirs.get_x_lb()[bounded])
    assert np.array_equal(system.state_high[bounded], theirs.get_x_ub()[bounded])
    assert set(system.angle_dims) == {"unicycle1_v0": {2}, "unicycle2_v0": {2},
                                      "quad2d_v0": {2}, "acrobot_v0": {0, 1},
                                      "integrator2_2d_v0": set()}[robot]


def test_the_plan_figure_draws_the_obstacles_and_the_body_along_the_path():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.patches import Polygon

    from rrtcolearn import planners
    from rrtcolearn.plotting import tree_figure
    p = db.read_problem("unicycle1_v0/parallelpark_0")
    system = db.make_system(p)
    plan = planners.make("random-rrt").solve(
        db.planning_problem(p, system), TerminationCondition(time_limit=None,
                                                             max_iterations=20000), seed=0)
    fig = tree_figure(plan, system.state_names)
    ax = fig.axes[0]
    polys = [q.get_xy()[:4] for q in ax.patches if isinstance(q, Polygon)]
    obstacles = [q for q in polys if np.allclose(q.mean(0), [0.3, 0.3]) or
                 np.allclose(q.mean(0), [1.1, 0.3]) or np.allclose(q.mean(0), [2.7, 0.3])]
    assert len(obstacles) == 3 and len(polys) == 3 + 12
    first = [q for q in polys if np.allclose(q.mean(0), p.start[:2])]
    assert first and np.allclose(np.ptp(first[0], 0), [0.5, 0.25])  # the body at the start
    assert ax.get_xlabel() == "x" and ax.get_aspect() == 1.0


def test_the_command_line_names_a_bad_problem_in_one_line(tmp_path):
    # the whole `run --dynobench` (fit included) takes minutes even tiny: docs/dynobench.md
    # gives the commands run by hand; here only that a bad name is one line, no traceback
    from typer.testing import CliRunner

    from rrtcolearn.cli import app

    bad = CliRunner().invoke(app, ["run", "--dynobench", "nowhere/x", "--out",
                                   str(tmp_path / "x")])
    assert bad.exit_code == 2 and bad.output.strip().count("\n") == 0, bad.output
    assert bad.output.startswith("error: nowhere/x: not a problem dynobench ships")


@pytest.mark.parametrize("robot", ["acrobot_v0", "integrator2_2d_v0"])
def test_the_posed_configuration_rebuilds_the_same_problem(robot):
    # what `run --dynobench` records (the acrobot's links by their function's name) gives,
    # through the configuration, the problem `planning_problem` poses
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config
    p = db.read_problem({"acrobot_v0": "acrobot_v0/swing_up_obs_hard",
                         "integrator2_2d_v0": "integrator2_2d_v0/park"}[robot])
    cfg = load_config(None, [], options=db.config_options(p))
    system = db.make_system(p)
    assert cfg.system.time_weight == {"acrobot_v0": 200.0, "integrator2_2d_v0": 4.0}[robot]
    start, goal = pipeline.query_states(cfg, system)
    posed = pipeline.make_problem(system, cfg, start, goal, 0.1)
    direct = db.planning_problem(p, system)
    assert np.array_equal(posed.start, direct.start) and np.array_equal(posed.goal, direct.goal)
    x = np.random.default_rng(4).uniform(system.state_low, system.state_high, (800, 4))
    if robot != "acrobot_v0":
        x[:, :2] = np.random.default_rng(5).uniform(p.low, p.high, (800, 2))
    assert np.array_equal(posed.validity(x), direct.validity(x)) and not posed.validity(x).all()
