"""dynobench interop (rrtcolearn.dynobench): the reader on every problem the package ships,
one-line errors naming the file and key, the exact body against dynobench's own collision
checker (its compiled bindings: fcl), and plans exported in its result format."""

from pathlib import Path

import numpy as np
import pytest
import yaml

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
    assert p.dt == raw.get("dt", yaml.safe_load(
        (db.package_dir() / "models" / f"{p.robot}.yaml").read_text()).get("dt", 0.1))


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


@pytest.mark.parametrize("name", ["unicycle1_v0/parallelpark_0", "unicycle1_v0/kink_0",
                                  "unicycle1_v0/bugtrap_0", "quad2d_v0/quad_obs_column"])
def test_the_exact_body_agrees_with_dynobenchs_checker_and_a_polygon_test(name):
    # dynobench's checker (fcl) is asked only where the exact test finds the body free: its
    # penetration query on a body deep in an obstacle can run for minutes (e.g.
    # [2.324, 0.211, -1.42] on parallelpark_0); where the body collides the reference is the
    # brute-force polygon test of test_geometry (segment crossings, point in polygon)
    from test_geometry import corners, polys_meet
    p = db.read_problem(name)
    rng = np.random.default_rng(7)
    x = np.zeros((1500, len(p.start)))
    x[:, :2] = rng.uniform(p.low, p.high, (1500, 2))
    x[:, 2] = rng.uniform(-np.pi, np.pi, 1500)
    mine = db.workspace(p).contains(x)
    assert 50 < mine.sum() < 1450
    theirs = db.dynobench_distances(p, x[~mine])
    assert np.all(theirs > -1e-5)  # fcl's geometry is in single precision
    w, h = p.model["size"]
    for xi in x[mine]:
        assert any(polys_meet(corners(*xi[:2], w, h, xi[2]), corners(*o.center, *o.size, 0.0))
                   for o in p.obstacles)


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


def test_unbuilt_models_say_so():
    p = db.read_problem("acrobot_v0/swing_up_obs")
    with pytest.raises(db.DynobenchError, match=r"robots\[0\]\.type: acrobot_v0 is read but not"):
        db.make_system(p)


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
