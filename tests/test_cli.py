"""The command line on a tiny configuration, and every bad input of the pipeline issue."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rrtcolearn.cli import app
from rrtcolearn.data.store import load_dataset
from rrtcolearn.pipeline import read_plan

# plans stop on the iteration budget, deterministic per seed; a setting cannot say "no time
# limit", so the time limit is a backstop no test's budget comes near
BACKSTOP = ["--set", "plan.time_limit=600"]
TINY = ["--set", "generate.n_simulations=3000", "--set", "clean.k_max=500",
        "--set", "plan.max_iterations=400", *BACKSTOP]


def invoke(*args: str):
    return CliRunner().invoke(app, list(args))


def assert_one_line_error(result, code: int = 2, contains: str = "") -> None:
    assert result.exit_code == code, result.output
    text = result.output.strip()
    assert "Traceback" not in text
    assert len(text.splitlines()) == 1, text
    assert text.startswith("error:")
    assert contains in text


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "tiny"
    result = invoke("run", "--seed", "3", "--out", str(out), *TINY)
    assert result.exit_code == 0, result.output
    return out


def test_run_writes_every_artefact(tiny_run):
    for name in ("config.toml", "dataset.npz", "cleaned.npz", "model.json", "plan.json",
                 "plan.png", "summary.json"):
        assert (tiny_run / name).is_file(), name
    cfg = (tiny_run / "config.toml").read_text()
    assert "n_simulations = 3000" in cfg and "seed = 3" in cfg
    summary = json.loads((tiny_run / "summary.json").read_text())
    assert summary["raw_points"] > summary["kept_points"] > 0
    assert not list(tiny_run.glob(".*.tmp"))
    # the goal funnel's length, derived from the fitted data, recorded with its reason
    info = json.loads((tiny_run / "model.json").read_text())
    assert info["config"]["plan"]["funnel_duration"] == info["max_duration"] > 0
    assert "the data's longest extremal" in info["config"]["derived"]["plan.funnel_duration"]


def test_steps_one_by_one_equal_the_run(tiny_run, tmp_path):
    out = tmp_path / "steps"
    for step in ("generate", "clean", "fit"):
        result = invoke(step, "--seed", "3", "--out", str(out), *TINY)
        assert result.exit_code == 0, result.output
    _a, ma = load_dataset(out / "cleaned.npz")
    _b, mb = load_dataset(tiny_run / "cleaned.npz")
    assert ma["sha256"] == mb["sha256"]
    query = ["plan", "--model", str(out), "--start=-3.14159,0", "--goal", "0,0",
             "--goal-tolerance", "0.3", "--seed", "2", "--max-iterations", "300",
             "--out", str(tmp_path / "p.json")]
    result = invoke(*query, "--plot")
    assert result.exit_code == 0, result.output
    plan = json.loads((tmp_path / "p.json").read_text())
    assert plan["goal_tolerance"] == 0.3 and plan["iterations"] <= 300
    assert (tmp_path / "p.png").is_file()
    # without --plot no picture, and the one of the earlier plan is not left beside it
    result = invoke(*query)
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "p.json").read_text())["path"] == plan["path"]
    assert not (tmp_path / "p.png").exists()


def test_plot_is_for_one_plan(tiny_run, tmp_path):
    queries = tmp_path / "q.jsonl"
    queries.write_text('{"start": [-3.0, 0.0], "goal": [0.0, 0.0]}\n')
    result = invoke("plan", "--model", str(tiny_run), "--queries", str(queries), "--plot")
    assert_one_line_error(result, contains="--plot")


@pytest.mark.parametrize("start, goal, tol, contains", [
    ("nan,0", "0,0", "0.1", "finite"),
    ("-3.14,0", "0,9", "0.1", "outside the state box"),
    ("1,a", "0,0", "0.1", "comma-separated"),
    ("1", "0,0", "0.1", "2 coordinates"),
    ("-3.14,0", "0,0", "0", "greater than 0"),
    ("-3.14,0", "0,0", "-1", "greater than 0"),
])
def test_bad_plan_queries(tiny_run, tmp_path, start, goal, tol, contains):
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), f"--start={start}", f"--goal={goal}",
                    f"--goal-tolerance={tol}", "--out", str(out))
    assert_one_line_error(result, contains=contains)
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_missing_and_corrupted_run_directories(tiny_run, tmp_path):
    result = invoke("plan", "--model", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p"))
    assert_one_line_error(result, contains="not found")
    broken = tmp_path / "broken"
    broken.mkdir()
    for name in ("model.json", "functions.npz", "config.toml"):
        (broken / name).write_bytes((tiny_run / name).read_bytes())
    raw = (broken / "functions.npz").read_bytes()
    (broken / "functions.npz").write_bytes(raw[: len(raw) // 3])
    result = invoke("plan", "--model", str(broken), "--out", str(tmp_path / "p.json"))
    assert_one_line_error(result, contains="functions.npz")
    (broken / "model.json").write_text("{not json")
    result = invoke("plan", "--model", str(broken), "--out", str(tmp_path / "p.json"))
    assert_one_line_error(result, contains="JSON")
    result = invoke("clean", "--out", str(tmp_path / "empty"))
    assert_one_line_error(result, contains="not found")


def test_unknown_and_mistyped_config_keys(tmp_path):
    out = tmp_path / "r"
    result = invoke("generate", "--out", str(out), "--set", "generate.n_simulation=10")
    assert_one_line_error(result, contains="did you mean 'n_simulations'")
    cfg = tmp_path / "c.toml"
    cfg.write_text("[clean]\nradius = 0.1\n")
    result = invoke("generate", "--out", str(out), "--config", str(cfg))
    assert_one_line_error(result, contains="unknown key 'clean.radius'")
    cfg.write_text("[generate]\nn_simulations = 'many'\n")
    result = invoke("generate", "--out", str(out), "--config", str(cfg))
    assert_one_line_error(result, contains="generate.n_simulations")
    cfg.write_text("[generate\n")
    result = invoke("generate", "--out", str(out), "--config", str(cfg))
    assert_one_line_error(result, contains="not valid TOML")
    result = invoke("generate", "--out", str(out), "--set", "system.name=rocket")
    assert_one_line_error(result, contains="unknown system")
    assert not out.exists()


def test_console_script_end_to_end(tmp_path):
    """The installed command itself, as a user runs it: a bad input is one line, exit 2."""
    exe = Path(sys.executable).with_name("rrtcolearn")
    proc = subprocess.run([str(exe), "plan", "--model", str(tmp_path), "--start=nan,0"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.startswith("error:")


def test_same_seed_same_dataset(tmp_path):
    digests = []
    for name in ("a", "b"):
        result = invoke("generate", "--seed", "9", "--out", str(tmp_path / name),
                        "--set", "generate.n_simulations=500")
        assert result.exit_code == 0, result.output
        digests.append(load_dataset(tmp_path / name / "dataset.npz")[1]["sha256"])
    assert digests[0] == digests[1]
    assert np.array_equal(load_dataset(tmp_path / "a" / "dataset.npz")[0].x1,
                          load_dataset(tmp_path / "b" / "dataset.npz")[0].x1)


@pytest.mark.parametrize("spec, contains", [
    ("box:-1,-1,1,1", "goal"),
    ("box:1,2,3", "low and high"),
    ("circle:0,0,1", "unknown type"),
    ("box:a,b,c,d", "numbers"),
])
def test_bad_obstacles(tiny_run, tmp_path, spec, contains):
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), "--obstacle", spec, "--out", str(out))
    assert_one_line_error(result, contains=contains)
    assert not out.exists()


def test_run_checks_the_query_before_the_offline_steps(tmp_path):
    """A goal inside an obstacle is refused before any simulation is generated."""
    out = tmp_path / "run"
    result = invoke("run", "--out", str(out), *TINY, "--obstacle", "box:-1,-1,1,1")
    assert_one_line_error(result, contains="inside an obstacle")
    assert not (out / "dataset.npz").exists()


def test_plan_obstacles_replace_the_runs(tmp_path):
    """A model whose run had an obstacle plans with it unless the plan gives its own
    obstacles, which replace it (the same box given again is not doubled)."""
    run = tmp_path / "with-box"
    result = invoke("run", "--out", str(run), "--set", "generate.n_simulations=300",
                    "--set", "clean.k_max=100", "--set", "plan.max_iterations=50", *BACKSTOP,
                    "--obstacle", "box:-2,0.3,-1.2,2.5")
    assert result.exit_code == 0, result.output
    plans = {}
    for name, extra in (("own", []), ("given", ["--obstacle", "box:-2,0.3,-1.2,2.5",
                                                "--obstacle", "halfplane:0,-1,2.8"])):
        out = tmp_path / f"{name}.json"
        result = invoke("plan", "--model", str(run), "--max-iterations", "50", *extra,
                        "--out", str(out))
        assert result.exit_code == 0, result.output
        plans[name] = json.loads(out.read_text())["obstacles"]
    assert [o["type"] for o in plans["own"]] == ["box"]
    assert [o["type"] for o in plans["given"]] == ["box", "halfplane"]


def test_the_summary_gives_inputs_limits_of_their_own(tiny_run):
    """Where the inputs share no single bound the summary lists each input's, instead of a
    bare ``u_max`` of none that reads as unbounded."""
    import dataclasses

    from rrtcolearn import pipeline
    from rrtcolearn.cli.planning import plan_summary

    p = pipeline.plan(pipeline.load_model(tiny_run), [-3.0, 0.0], [0.0, 0.0], 0.3, 1,
                      max_iterations=20)
    shared = plan_summary(dataclasses.replace(p, input_low=np.array([-2.0]),
                                              input_high=np.array([2.0])))
    assert shared["u_max"] == 2.0 and "input_limits" not in shared
    own = plan_summary(dataclasses.replace(p, input_low=np.array([-1.0, -1.5]),
                                           input_high=np.array([1.0, 1.5])))
    assert own["u_max"] is None and own["limit_mode"] == "saturate"
    assert own["input_limits"] == "[-1, 1], [-1.5, 1.5]"


def test_a_file_given_as_the_model_is_named_as_such(tiny_run):
    result = invoke("plan", "--model", str(tiny_run / "plan.json"))
    assert_one_line_error(result, contains="is a file, not a run directory")


def test_u_max_and_obstacle_options(tiny_run, tmp_path):
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), "--u-max", "3", "--obstacle",
                    "box:-2,0.3,-1.2,2.5", "--max-iterations", "200", "--out", str(out))
    assert result.exit_code == 0, result.output
    d = json.loads(out.read_text())
    assert d["u_max"] == 3.0 and d["obstacles"][0]["low"] == [-2.0, 0.3]
    assert d["max_abs_u"] <= 3.0
    result = invoke("generate", "--out", str(tmp_path / "g"), "--u-max", "1",
                    "--set", "generate.n_simulations=200", "--set", "system.time_weight=0.1")
    assert result.exit_code == 0, result.output
    assert "u_max = 1.0" in (tmp_path / "g" / "config.toml").read_text()
    result = invoke("generate", "--out", str(tmp_path / "h"), "--u-max", "-1")
    assert_one_line_error(result, contains="u_max")


def test_unusable_output_paths(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    result = invoke("generate", "--out", str(afile), "--set", "generate.n_simulations=10")
    assert_one_line_error(result, code=2, contains="not a directory")
    result = invoke("generate", "--out", "/proc/not-writable", "--set",
                    "generate.n_simulations=10")
    assert_one_line_error(result, code=3, contains="cannot read or write")


def test_system_from_a_users_module(tmp_path, monkeypatch):
    monkeypatch.chdir(Path(__file__).parents[1])
    out = tmp_path / "damped"
    result = invoke("run", "--system", "examples.damped_pendulum:make_damped_pendulum",
                    "--out", str(out), "--set", "generate.n_simulations=3000",
                    "--set", "plan.max_iterations=50", "--set", "plan.goal_tolerance=0.3")
    assert result.exit_code == 0, result.output
    plan = json.loads((out / "plan.json").read_text())
    assert plan["system"] == "damped_pendulum"
    assert "damped_pendulum" in (out / "config.toml").read_text()
    for spec, contains in (("nosuchmodule:thing", "cannot import 'nosuchmodule' (No module "
                                                  "named 'nosuchmodule'); it is looked for in "
                                                  "the current directory and on PYTHONPATH"),
                           ("examples.damped_pendulum:nothing", "has no"),
                           ("rocket", "unknown system")):
        result = invoke("generate", "--system", spec, "--out", str(tmp_path / "x"))
        assert_one_line_error(result, contains=contains)


def test_error_messages_stay_one_literal_line(tmp_path):
    """Control characters and rich markup in user input are shown escaped, never obeyed."""
    for args in (["generate", "--config", "\x1e0"], ["generate", "--config", "[/]x"],
                 ["generate", "--set", "[red]a=1"]):
        result = invoke(*args)
        assert_one_line_error(result)
    assert "\\x1e0" in invoke("generate", "--config", "\x1e0").output
    assert "[/]x" in invoke("generate", "--config", "[/]x").output


@pytest.mark.parametrize("name, query", [
    ("pendulum", []), ("double_integrator", []), ("acrobot", []),
    # the full swing-up takes about 20 s of CPU with a 100 000-simulation network (README):
    # from 0.54 rad short of upright a 2 000-simulation model reaches the goal
    ("cartpole", ["--set", "plan.start=[0.0, 2.6, 0.0, 0.0]"])])
def test_run_works_for_every_shipped_system(name, query, tmp_path):
    """`rrtcolearn run --system NAME` writes the same artefacts for every shipped system, with
    the system's recommended configuration under the user's settings, and solves its query
    within an iteration budget (seed 1: pendulum in 755 iterations, double integrator 184,
    acrobot 545, cart-pole 210)."""
    out = tmp_path / name
    result = invoke("run", "--system", name, "--out", str(out), "--seed", "1",
                    "--set", "generate.n_simulations=2000", "--set", "clean.k_max=300",
                    "--set", "plan.max_iterations=2000", *BACKSTOP,
                    "--set", "learn.mlp_max_iter=5", *query)
    assert result.exit_code == 0, result.output
    for artefact in ("config.toml", "dataset.npz", "cleaned.npz", "model.json", "plan.json",
                     "plan.png", "summary.json"):
        assert (out / artefact).is_file(), artefact
    plan = json.loads((out / "plan.json").read_text())
    assert plan["system"] == name
    assert plan["solved"] and plan["status"] == "exact" and plan["iterations"] < 2000
    assert plan["final_goal_distance"] <= plan["goal_tolerance"]
    cfg = (out / "config.toml").read_text()
    assert "n_simulations = 2000" in cfg  # the user's setting wins over the recommended one
    if name == "cartpole":  # ... which applies where the user is silent
        assert 'name = "cartpole-swingup"' in cfg and "control_samples = 16" in cfg
        assert 'learner = "mlp"' in cfg and (out / "functions.npz").is_file()


def test_run_name_follows_the_system():
    """Without --out a user system's run does not land in the pendulum's directory."""
    from rrtcolearn.cli.common import run_name
    from rrtcolearn.config import load_config

    assert run_name(load_config()) == "pendulum-swingup"
    user = load_config(overrides=['system.name="examples.damped_pendulum:make_damped_pendulum"'])
    assert run_name(user) == "examples.damped_pendulum-make_damped_pendulum"
    named = load_config(overrides=['name="mine"', 'system.name="double_integrator"'])
    assert run_name(named) == "mine"
    # a registered system's recommended configuration names its runs
    assert run_name(load_config(overrides=['system.name="cartpole"'])) == "cartpole-swingup"


def test_plan_queries_from_a_file(tiny_run, tmp_path):
    lines = [{"start": [-3.14159, 0.0], "goal": [0.0, 0.0], "goal_tolerance": 0.3, "seed": 4},
             {"start": [-1.0, 0.5], "goal": [0.0, 0.0]},
             {"start": [-2.0, -1.0], "goal": [0.0, 0.0], "seed": 9}]
    jsonl = tmp_path / "q.jsonl"
    jsonl.write_text("\n".join(json.dumps(q) for q in lines) + "\n")
    csv_file = tmp_path / "q.csv"
    csv_file.write_text('start,goal,goal_tolerance,seed\n"-3.14159,0","0,0",0.3,4\n'
                        '"-1,0.5","0,0",,\n"-2,-1","0,0",,9\n')
    timing = {"planning_time_s", "planning_cpu_s", "sha256"}

    def plans(out):
        return [{k: v for k, v in read_plan(out / f"plan-{i:05d}.json").items()
                 if k not in timing} for i in range(3)]

    runs = {}
    for name, path, extra in (("jsonl", jsonl, ()), ("csv", csv_file, ()),
                              ("workers", jsonl, ("--workers", "2"))):
        out = tmp_path / name
        result = invoke("plan", "--model", str(tiny_run), "--queries", str(path), "--out",
                        str(out), "--max-iterations", "300", *extra)
        assert result.exit_code == 0, result.output
        runs[name] = plans(out)
        rows = list(csv.DictReader((out / "plans.csv").open()))
        assert [int(r["seed"]) for r in rows] == [4, 1, 9]  # no seed: the line's index
    # the same queries give the same plans, from either format and from worker processes
    assert runs["jsonl"] == runs["csv"] == runs["workers"]
    assert runs["jsonl"][0]["goal_tolerance"] == 0.3 and runs["jsonl"][1]["seed"] == 1
    # one query of the file, planned alone, is the same plan
    one = tmp_path / "one.json"
    result = invoke("plan", "--model", str(tiny_run), "--start=-2,-1", "--goal=0,0",
                    "--seed", "9", "--max-iterations", "300", "--out", str(one))
    assert result.exit_code == 0, result.output
    alone = {k: v for k, v in read_plan(one).items() if k not in timing}
    assert alone == runs["jsonl"][2]


@pytest.mark.parametrize("content, contains", [
    ('{"start": [0, 0]}\n', "goal is missing"),
    ('{"start": [0, 0], "goal": [0, 0, 1]}\n', "needs 2 values"),
    ('{"start": [0, 0], "goal": [0, 0], "tolerance": 1}\n', "unknown field 'tolerance'"),
    ('{"start": [0, 0], "goal": [0, 0]}\nnot json\n', "line 2: not JSON"),
    ('{"start": [9, 0], "goal": [0, 0]}\n', "line 1: start theta"),
    ('{"start": [0, 0], "goal": [0, 0], "seed": -1}\n', "seed must be a non-negative"),
    ("", "no queries"),
])
def test_bad_query_files(tiny_run, tmp_path, content, contains):
    path = tmp_path / "q.jsonl"
    path.write_text(content)
    result = invoke("plan", "--model", str(tiny_run), "--queries", str(path), "--out",
                    str(tmp_path / "out"))
    assert_one_line_error(result, contains=contains)
    assert not (tmp_path / "out").exists()  # nothing planned before every query checks out
    result = invoke("plan", "--model", str(tiny_run), "--queries", str(path), "--start=0,0")
    assert_one_line_error(result)

def test_experiment_on_a_users_system(tmp_path, monkeypatch):
    """`experiment --system module:attribute --quick`: the system's standard query is the one
    problem, each peer that supports it runs beside rrtcolearn, the others are named."""
    monkeypatch.chdir(Path(__file__).parents[1])
    out = tmp_path / "exp"
    result = invoke("experiment", "--system", "examples.damped_pendulum:make_damped_pendulum",
                    "--quick", "--out", str(out), "--set", "generate.n_simulations=3000",
                    "--set", "plan.goal_tolerance=0.3", "--set", "experiment.max_iterations=3000",
                    "--set", "experiment.runs_per_epoch=2", "--set", "experiment.peer_u_max=2.0",
                    "--set", 'experiment.planners=["rrtcolearn", "random-rrt", "direct"]')
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["system"] == "damped_pendulum" and summary["main_problem"] == "standard"
    assert set(summary["planners"]["standard"]) == {"rrtcolearn", "random-rrt"}
    assert "pendulum" in summary["skipped_planners"]["direct on standard"]
    assert (out / "ompl" / "damped_pendulum-standard.log").is_file()
    assert (out / "benchmark.db").is_file() and "random-rrt" in (out / "report.md").read_text()
    result = invoke("experiment", "--system", "rocket", "--out", str(tmp_path / "x"))
    assert_one_line_error(result, contains="unknown system")


def test_plan_anytime_writes_its_progress(tiny_run, tmp_path):
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), "--anytime", "--max-iterations", "1500",
                    "--out", str(out))
    assert result.exit_code == 0, result.output
    a = json.loads(out.read_text())["anytime"]
    assert a["scheme"] == "restarts+shortcut" and a["solves"] >= 1
    assert "anytime_solves" in result.output


def test_plan_polish_records_both_costs(tiny_run, tmp_path):
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), "--max-iterations", "1500",
                    "--set", "plan.polish=true", "--out", str(out))
    assert result.exit_code == 0, result.output
    d = json.loads(out.read_text())
    assert "anytime" not in d and d["polish"]["cost"] == d["path_cost"]
    assert d["polish"]["cost"] <= d["polish"]["first_cost"]
    assert "first_solution_cost" in result.output and "polished_cost" in result.output


def test_progress_is_lines_on_stderr_without_a_terminal(capsys):
    """Without a terminal (a log, a pipe, a batch job) long work reports plain lines on
    stderr, at most one per interval, the first after one interval: short work prints
    nothing."""
    from rrtcolearn.cli.common import LineProgress, progress_bar

    assert isinstance(progress_bar(), LineProgress)  # pytest's output is no terminal
    quiet = LineProgress(every=3600.0)
    quiet.advance(quiet.add_task("fast", total=5), 5)
    assert capsys.readouterr().err == ""
    p = LineProgress(every=0.0)
    with p:
        t = p.add_task("generate", total=10)
        p.advance(t, 3)
        p.update(t, description="clean", completed=7)
    err = capsys.readouterr().err.splitlines()
    assert err[0].endswith("generate: 3/10") and err[1].endswith("clean: 7/10")


def test_a_model_of_a_name_registered_elsewhere(tmp_path, monkeypatch):
    """A name given to `register` lives in one Python session: the command line says so
    and plans (and exports) the model with --system module:attribute of the same system."""
    from examples.damped_pendulum import make_damped_pendulum

    from rrtcolearn import pipeline, systems
    from rrtcolearn.config import load_config

    monkeypatch.chdir(Path(__file__).parents[1])
    monkeypatch.setattr(systems, "_REGISTRY", dict(systems._REGISTRY))
    monkeypatch.setattr(systems, "_CONFIGS", dict(systems._CONFIGS))
    systems.register("damped_pendulum", make_damped_pendulum)
    cfg = load_config(overrides=['system.name="damped_pendulum"', "generate.n_simulations=3000",
                                 "clean.k_max=500"])
    run = tmp_path / "registered"
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    pipeline.fit(cfg, run)
    del systems._REGISTRY["damped_pendulum"]  # as in a new session
    query = ["--start=-3.1,0", "--goal", "0,0", "--goal-tolerance", "0.3",
             "--set", "plan.max_iterations=300"]
    result = invoke("plan", "--model", str(run), *query, "--out", str(tmp_path / "p.json"))
    assert_one_line_error(result, contains="not registered in this process")
    result = invoke("plan", "--model", str(run), "--system", "cartpole", *query,
                    "--out", str(tmp_path / "p.json"))
    assert_one_line_error(result, contains="builds system 'cartpole'")
    spec = "examples.damped_pendulum:make_damped_pendulum"
    result = invoke("plan", "--model", str(run), "--system", spec, *query,
                    "--out", str(tmp_path / "p.json"))
    assert result.exit_code == 0, result.output
    plan = read_plan(tmp_path / "p.json")
    assert plan["system"] == "damped_pendulum" and plan["config"]["system"]["name"] == spec
    result = invoke("export", str(tmp_path / "p.json"))  # the plan names its module
    assert result.exit_code == 0, result.output


def test_plan_refuses_settings_it_would_ignore(tiny_run, tmp_path):
    """Only [plan] and a plan-time u_max change at plan time; a value equal to the model's
    (a configuration file shared with `run`) is fine, another is refused, not recorded in
    the plan file and ignored."""
    query = ["--start=-3,0", "--goal", "0,0", "--out", str(tmp_path / "p.json")]
    for setting in ("system.time_weight=0.1", "learn.n_neighbors=10", 'system.name="cartpole"'):
        result = invoke("plan", "--model", str(tiny_run), *query, "--set", setting)
        assert_one_line_error(result, contains=f"{setting.split('=')[0]}: a plan uses the "
                              "model's settings")
    shared = tmp_path / "shared.toml"
    shared.write_text('[system]\nname = "pendulum"\ntime_weight = 1.0\n[plan]\ngoal_bias = 0.3\n')
    result = invoke("plan", "--model", str(tiny_run), *query, "--config", str(shared))
    assert result.exit_code == 0, result.output
    assert read_plan(tmp_path / "p.json")["config"]["plan"]["goal_bias"] == 0.3


@pytest.mark.parametrize("setting", ["plan.goal_bias=true", "plan.stall_iterations=false",
                                     "generate.n_simulations=true", "plan.start=[true,0]",
                                     "plan=3"])
def test_true_and_false_are_no_numbers(setting, tmp_path):
    result = invoke("generate", "--out", str(tmp_path / "x"), "--set", setting)
    assert_one_line_error(result, contains="section" if setting == "plan=3"
                          else "not true/false")
    assert not (tmp_path / "x").exists()


def test_a_registered_systems_own_defaults_config_applies(monkeypatch):
    """register(name, factory) without a config takes the system's defaults["config"], as
    naming it module:attribute does (the README's pattern)."""
    from examples.sparse_rrt_acrobot import TASK_GOAL_RADIUS, make_acrobot

    from rrtcolearn import systems
    from rrtcolearn.config import load_config

    monkeypatch.setattr(systems, "_REGISTRY", dict(systems._REGISTRY))
    monkeypatch.setattr(systems, "_CONFIGS", dict(systems._CONFIGS))
    systems.register("my_acrobot", make_acrobot)
    by_name = load_config(overrides=['system.name="my_acrobot"'])
    by_module = load_config(overrides=['system.name="examples.sparse_rrt_acrobot:make_acrobot"'])
    assert by_name.plan.goal_tolerance == by_module.plan.goal_tolerance == TASK_GOAL_RADIUS
    assert by_name.plan == by_module.plan


@pytest.mark.parametrize("setting, contains", [
    ('plan.goal_tolerance="0.2"', "must be a number, not text"),
    ('plan.obstacles=[{type="halfplane", normal=[0,1], offset="2.8"}]',
     "must be a number, not text"),
    ('plan.obstacles=[{type="box", lo=[0,0], high=[1,1]}]', "did you mean 'low'?"),
    ('plan.obstacles=[{type="box", low=[0,0], high=[1,1], margin=1}]',
     "known keys: type, low, high"),
    ("plan.goal=[1,", "'[1,' is not a valid TOML value"),
])
def test_obstacle_and_number_settings_as_written(setting, contains, tmp_path):
    """A quoted number is text, not silently a number; a misspelt obstacle key gets the
    suggestion every other section gets."""
    result = invoke("generate", "--out", str(tmp_path / "x"), "--set", setting)
    assert_one_line_error(result, contains=contains)


# --------------------------------------------------------------------------- options and listings


def test_version_is_the_projects():
    import tomllib

    version = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())[
        "project"]["version"]
    for argv in (["--version"], ["--version", "plan", "--bogus"]):  # eager: before the rest
        result = invoke(*argv)
        assert result.exit_code == 0 and result.output == f"rrtcolearn {version}\n"


def test_systems_lists_every_registered_system_one_per_line():
    from rrtcolearn.systems import list_systems, make

    result = invoke("systems")
    assert result.exit_code == 0, result.output
    # one line each, however long the description (no wrapping at a console width)
    assert result.output.splitlines() == [f"{n}: {make(n).description}" for n in list_systems()]
    assert {"pendulum", "double_integrator", "cartpole", "acrobot"} <= set(list_systems())


def test_inspect_lists_every_artefact_with_its_size_and_digest(tiny_run):
    import hashlib

    result = invoke("inspect", str(tiny_run))
    assert result.exit_code == 0, result.output
    rows = {line.split()[0]: line.split()[1:] for line in result.output.splitlines()}
    files = sorted(p for p in tiny_run.iterdir() if p.is_file() and not p.name.startswith("."))
    assert sorted(rows) == [p.name for p in files]
    for p in files:
        kind, size, sha = rows[p.name]
        assert int(size) == p.stat().st_size and len(sha) == 64
        assert kind == ("functions" if p.name == "functions.npz" else {
            ".npz": "dataset", ".json": "json", ".toml": "toml"}.get(p.suffix, "file"))
        if kind == "file":  # anything else: the digest of its bytes
            assert sha == hashlib.sha256(p.read_bytes()).hexdigest()
    result = invoke("inspect", str(tiny_run / "nowhere"))
    assert_one_line_error(result, contains="not found")


def test_time_limit_option_stops_the_plan(tiny_run, tmp_path):
    """--time-limit is the planner's wall-clock limit (a test of the limit: generous margin).
    The goal funnel is off: its multiple-shooting chains land on the goal's centre to 1e-8
    and better, so a tolerance of 1e-9 alone no longer makes the query unsolvable."""
    out = tmp_path / "p.json"
    result = invoke("plan", "--model", str(tiny_run), "--goal-tolerance", "1e-9",
                    "--time-limit", "0.5", "--max-iterations", "100000000",
                    "--set", "plan.goal_funnel=0", "--out", str(out))
    assert result.exit_code == 0, result.output
    plan = read_plan(out)
    assert plan["config"]["plan"]["time_limit"] == 0.5
    assert not plan["solved"] and plan["status"] == "approximate"
    assert 0.5 <= plan["planning_time_s"] < 60 and plan["iterations"] < 100_000_000


def test_first_solution_overrides_an_anytime_setting(tiny_run, tmp_path):
    query = ["plan", "--model", str(tiny_run), "--seed", "4", "--max-iterations", "1500",
             "--set", "plan.anytime=true"]
    assert invoke(*query, "--first-solution", "--out", str(tmp_path / "a.json")).exit_code == 0
    assert invoke(*query[:-2], "--out", str(tmp_path / "b.json")).exit_code == 0
    assert invoke(*query, "--out", str(tmp_path / "c.json")).exit_code == 0
    first, plain, anytime = (read_plan(tmp_path / f"{n}.json") for n in "abc")
    assert first["config"]["plan"]["anytime"] is False and "anytime" not in first
    assert first["path"] == plain["path"] and first["solved"]
    assert anytime["config"]["plan"]["anytime"] is True and anytime["anytime"]["solves"] >= 1


def test_offline_budget_chooses_the_simulations(tmp_path):
    """--offline-budget runs the convergence test; a budget smaller than one stage stops it
    after the first (a quarter of the derived default), and the choice says why."""
    from rrtcolearn.config import read_toml

    out = tmp_path / "b"
    result = invoke("generate", "--out", str(out), "--offline-budget", "0.001",
                    "--set", "generate.chunk_size=500", "--set", "generate.max_cost=2.0")
    assert result.exit_code == 0, result.output
    cfg = read_toml(out / "config.toml")
    n = cfg["generate"]["n_simulations"]
    assert n == 10_000  # the pendulum's derived 40 000 / 4
    reason = cfg["derived"]["generate.n_simulations"]
    assert "offline budget 0.001 s CPU" in str(reason), reason
    assert load_dataset(out / "dataset.npz")[1]["config"]["generate"]["n_simulations"] == n


def _generated_digest(tmp_path: Path, name: str, *options: str) -> str:
    out = tmp_path / name
    result = invoke("generate", "--out", str(out), "--seed", "2", "--set",
                    "generate.n_simulations=400", "--set", "generate.chunk_size=100", *options)
    assert result.exit_code == 0, result.output
    return load_dataset(out / "dataset.npz")[1]["sha256"]


def test_dask_options_give_the_serial_dataset(tmp_path):
    """--dask-local N starts a local cluster; --scheduler ADDRESS uses a running one; the data
    are the serial run's either way. Both at once, or no workers, is a one-line error."""
    import distributed

    serial = _generated_digest(tmp_path, "serial")
    assert _generated_digest(tmp_path, "local", "--dask-local", "1") == serial
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        assert _generated_digest(tmp_path, "remote", "--scheduler",
                                 cluster.scheduler_address) == serial
    for bad, message in ((["--dask-local", "2", "--scheduler", "tcp://x:1"], "either"),
                         (["--dask-local", "0"], "at least 1")):
        result = invoke("generate", "--out", str(tmp_path / "x"), *bad)
        assert_one_line_error(result, contains=message)
