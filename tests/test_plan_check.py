"""`evaluate.check_plan`: a plan file is what it claims. A real plan passes; every way a
hand-edited file (its checksum recomputed, so `read_plan` lets it through) can lie or be
malformed is a one-line PlanCheckError naming the field, the edge and by how much."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest
from tests.conftest import pendulum_edge

from rrtcolearn import pipeline
from rrtcolearn.config import load_config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import json_checksum
from rrtcolearn.errors import ArtefactError
from rrtcolearn.evaluate import PlanCheckError, check_plan, resimulate
from rrtcolearn.pipeline import FittedModel, fit_functions, system_from_config

U_MAX = 1.0


@pytest.fixture(scope="module")
def model() -> FittedModel:
    """The pendulum saturated at |u| <= 1 on a small dataset (about 2 s): its plans mix
    extremal and random-control edges and record an input box."""
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "generate.n_simulations=10000"])
    system = system_from_config(cfg)
    data, _ = generate_data(system, 1, cfg.generate.n_simulations)
    cleaned, _ = clean_data(data, seed=1)
    return FittedModel(system, cfg, fit_functions(system, cleaned, cfg),
                       float(cleaned.duration.max()), cfg.generate.max_state_distance)


@pytest.fixture(scope="module")
def plan_file(model, tmp_path_factory):
    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000)
    assert p.solved
    path = tmp_path_factory.mktemp("plan") / "plan.json"
    pipeline.write_plan(p, path)
    kinds = {e["control"] is None for e in json.loads(path.read_text())["path"]}
    assert kinds == {True, False}, "the plan should hold both kinds of edge"
    return path


def _check(d: dict, **kw) -> dict:
    """What `rrtcolearn export` does with a plan file's content."""
    return check_plan(pipeline.plan_system(d), d, **kw)


def _tampered(plan_file, tmp_path, edit) -> dict:
    """The plan file edited by hand and its checksum recomputed: `read_plan` accepts it."""
    d = json.loads(plan_file.read_text())
    edit(d)
    d["sha256"] = json_checksum(d)
    out = tmp_path / "tampered.json"
    out.write_text(json.dumps(d))  # NaN written as a hand-edited file may hold it
    return pipeline.read_plan(out)


def _extremal(d: dict) -> int:
    return next(k for k, e in enumerate(d["path"]) if e["control"] is None)


def _control(d: dict) -> int:
    return next(k for k, e in enumerate(d["path"]) if e["control"] is not None)


def test_a_good_plan_passes_with_its_figures(model, plan_file):
    d = pipeline.read_plan(plan_file)
    r = _check(d)
    assert r["edges"] == len(d["path"])
    # an independent re-simulation (tests/conftest.py: the paper's Eqs. 6-7 and the held
    # input in plain numpy RK4, u* clipped to U_MAX) reproduces every edge's end and cost, so
    # what the file records and what check_plan compares it with are right, not only alike
    cost, u_abs = 0.0, 0.0
    for e in d["path"]:
        states, u, c = pendulum_edge(e, d["time_weight"], d["dt"], U_MAX)
        np.testing.assert_allclose(states[0], e["from"], rtol=0, atol=0)
        np.testing.assert_allclose(states[-1], e["to"], rtol=0, atol=1e-10)
        assert c == pytest.approx(e["cost"], rel=1e-10)
        cost, u_abs = cost + c, max(u_abs, float(np.abs(u).max()))
    assert r["path_cost"] == pytest.approx(cost, rel=1e-10)
    assert r["max_abs_u"] == pytest.approx(u_abs, rel=1e-10) and u_abs <= U_MAX + 1e-12
    # the planner and check_plan run one compiled RK4 at one step: on one machine the gaps
    # are exactly zero (`PLAN_CHECK_RTOL`); consistency only, the check above is the one
    # against a reference
    assert r["max_gap"] == 0.0 and r["max_cost_gap"] == 0.0 and r["max_join_gap"] == 0.0
    assert r["path_cost"] == pytest.approx(d["path_cost"], rel=1e-12)
    assert r["path_duration"] == pytest.approx(
        sum(round(e["duration"] / d["dt"]) for e in d["path"]) * d["dt"], rel=1e-12)
    assert r["path_duration"] == pytest.approx(d["path_duration"], rel=1e-12)
    assert r["max_abs_u"] == d["max_abs_u"] <= U_MAX
    assert r["end_goal_distance"] == pytest.approx(d["final_goal_distance"], rel=1e-12)
    assert r["end_goal_distance"] <= d["goal_tolerance"]
    assert r["goal_checked"] and r["goal_test"] == "distance to the goal"
    assert r["state_constraints_checked"] and r["obstacles"] == 0
    # one source of truth: `resimulate`'s figures, and the same for the `Plan` itself
    for key, value in resimulate(model.system, d).items():
        assert r[key] == value, key
    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000)
    assert check_plan(model.system, p) == r


def test_unsolved_plans_pass_and_their_distance_is_checked(model):
    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=1, time_limit=None,
                      max_iterations=3)
    d = json.loads(json.dumps(p.to_dict()))
    assert d["status"] in ("approximate", "timeout")
    r = _check(d)
    assert r["end_goal_distance"] == pytest.approx(d["final_goal_distance"], rel=1e-12)
    d["final_goal_distance"] = 0.05
    with pytest.raises(PlanCheckError, match=r"final_goal_distance is recorded as 0\.05"):
        _check(d)


def test_weighted_wrapped_goal_and_obstacles_pass(model):
    cfg = load_config(overrides=[f"system.u_max={U_MAX}", "generate.n_simulations=10000",
                                 "plan.wrap_goal=true", "plan.goal_weights=[1.0, 0.5]",
                                 'plan.obstacles=[{type="box", low=[-1.0, -1.0], '
                                 'high=[-0.5, 1.0]}]'])
    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=0, config=cfg, time_limit=None,
                      max_iterations=20_000)
    assert p.solved
    d = json.loads(json.dumps(p.to_dict()))
    r = _check(d)
    assert r["obstacles"] == 1
    assert r["goal_test"] == "weighted distance to the goal, angles modulo a turn"
    assert r["end_goal_distance"] == pytest.approx(d["final_goal_distance"], rel=1e-12)
    # the recorded wrapping must be the configuration's
    d["goal_angles"] = []
    with pytest.raises(PlanCheckError, match="disagree with the recorded configuration"):
        _check(d)


def test_a_user_goal_function_is_checked_when_given_or_marked(model):
    def goal_fn(x):  # the angle alone: omega free
        return np.abs(np.atleast_2d(x)[:, 0])

    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000, goal_fn=goal_fn)
    assert p.solved
    d = json.loads(json.dumps(p.to_dict()))
    r = _check(d, goal_fn=goal_fn)
    assert r["goal_checked"] and r["goal_test"] == "the goal function given"
    assert r["end_goal_distance"] == pytest.approx(d["final_goal_distance"], rel=1e-12)
    # the file records that a function it cannot hold was the test: the recorded distance
    # is all there is
    assert d["goal_test"] == "function"
    r = _check(d)
    assert not r["goal_checked"] and r["end_goal_distance"] is None
    assert "not re-checked" in r["goal_test"]
    d["final_goal_distance"] = 0.5
    with pytest.raises(PlanCheckError, match=r"final_goal_distance is 0\.5, not within"):
        _check(d)
    # a file without the field (written before it existed) is taken for the goal ball
    d = json.loads(json.dumps(p.to_dict()))
    del d["goal_test"]
    with pytest.raises(PlanCheckError, match=r"^(final_goal_distance is recorded|status is "
                                             r"'exact' but the path ends)"):
        _check(d)


def test_the_system_goal_region_is_re_checked(model):
    def region(x):  # the angle alone: omega free
        return np.abs(np.atleast_2d(x)[:, 0])

    own = dataclasses.replace(model.system, defaults={**model.system.defaults,
                                                      "goal_fn": region})
    p = pipeline.plan(model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000, goal_fn=region)
    d = json.loads(json.dumps(p.to_dict()))
    assert d.pop("goal_test") == "function"  # (passed in: not the system object's own)
    # a file that does not say: the plan's goal is the system's default goal, so its region
    # is the goal test
    r = check_plan(own, d)
    assert r["goal_checked"] and r["goal_test"] == "the goal region of system 'pendulum'"
    assert r["end_goal_distance"] == pytest.approx(d["final_goal_distance"], rel=1e-12)
    d["goal_test"] = "system"
    assert check_plan(own, d)["goal_checked"]
    with pytest.raises(PlanCheckError, match=r"^goal_test is 'system' but system 'pendulum' "
                                             r"has no goal region of its own$"):
        check_plan(model.system, d)
    d["final_goal_distance"] = 0.001
    with pytest.raises(PlanCheckError, match=r"^final_goal_distance is recorded as 0\.001, but "
                                             r"the path ends [\d.]+ from the goal \(the goal "
                                             r"region of system 'pendulum'\)$"):
        check_plan(own, d)


def _set(path: str, value):
    """An edit setting ``d[a][b]...`` (keys separated by dots; ``ext``/``ctl`` are the first
    extremal and random-control edge of the path)."""
    def edit(d):
        keys = path.split(".")
        node = d
        for key in keys[:-1]:
            node = _index(d, node, key)
        last = int(keys[-1]) if keys[-1].isdigit() else keys[-1]
        node[last] = value(node[last]) if callable(value) else value
    return edit


def _index(d, node, key):
    if key == "ext":
        return node[_extremal(d)]
    if key == "ctl":
        return node[_control(d)]
    return node[int(key)] if key.isdigit() else node[key]


def _delete(path: str):
    def edit(d):
        keys = path.split(".")
        node = d
        for key in keys[:-1]:
            node = _index(d, node, key)
        del node[keys[-1]]
    return edit


def _shift(path: str, j: int, by: float):
    def edit(d):
        node = d
        for key in path.split("."):
            node = _index(d, node, key)
        node[j] += by
    return edit


def _ext_index(plan_file) -> int:
    return _extremal(json.loads(plan_file.read_text()))


def _ctl_index(plan_file) -> int:
    return _control(json.loads(plan_file.read_text()))


# (edit, the message's pattern: "{ext}"/"{ctl}" become the edges' indices)
TAMPERS = {
    # the re-simulation
    "nan costate": (_set("path.ext.costate", [math.nan, 1.0]),
                    r"^path\[{ext}\]\.costate must be finite, got \[nan, 1\.0\]$"),
    "negative duration": (_set("path.1.duration", -1.0),
                          r"^path\[1\]\.duration is -1: an edge lasts a positive whole number "
                          r"of the plan's steps \(dt = 0\.01\)$"),
    "half a step": (_set("path.1.duration", lambda v: v + 0.005),
                    r"^path\[1\]\.duration is [\d.]+: an edge lasts a positive whole number"),
    "jump between edges": (_shift("path.2.from", 0, 0.1),
                           r"^path\[2\]\.from is 0\.1 from path\[1\]\.to: the path jumps$"),
    "first edge not at the start": (_shift("start", 1, 0.25),
                                    r"^path\[0\]\.from is 0\.25 from the start: the path "
                                    r"jumps$"),
    "to not re-simulated": (_shift("path.ext.to", 1, 1e-3),
                            r"^path\[{ext}\]: re-simulated for [\d.]+ s from its recorded from, "
                            r"it ends 0\.001 from its recorded to \(tolerance [\d.]+e-09\)$"),
    "control edge to": (_shift("path.ctl.to", 0, -2e-6),
                        r"^path\[{ctl}\]: re-simulated .* it ends 2e-06 from its recorded to"),
    "cost": (_set("path.ext.cost", lambda v: v + 0.01),
             r"^path\[{ext}\]: re-simulated, it costs [\d.]+, not the recorded [\d.]+ \(by "
             r"0\.01\)$"),
    "u_max the inputs break": (_set("u_max", 0.5),
                               r"^path\[\d+\]: input torque reaches -?[\d.]+ at t = [\d.]+ s, "
                               r"beyond the recorded u_max 0\.5 by [\d.]+$"),
    "input box the inputs break": (
        lambda d: d.update(u_max=None, input_low=[-0.5], input_high=[0.5]),
        r"^path\[\d+\]: input torque reaches -?[\d.]+ at t = [\d.]+ s, outside the "
        r"recorded input box \[-0\.5, 0\.5\] by [\d.]+$"),
    "goal moved, still exact": (_set("goal", [0.5, 0.0]),
                                r"^status is 'exact' but the path ends [\d.]+ from the goal "
                                r"\[0\.5, 0\.0\] \(distance to the goal\), beyond "
                                r"goal_tolerance 0\.1 \(the plan records final_goal_distance "
                                r"[\d.]+\)$"),
    "tolerance narrowed": (_set("goal_tolerance", 0.01),
                           r"^status is 'exact' but the path ends [\d.]+ from the goal"),
    "final distance": (_set("final_goal_distance", 0.001),
                       r"^final_goal_distance is recorded as 0\.001, but the path ends [\d.]+ "
                       r"from the goal \(distance to the goal\)$"),
    "marked a ball": (lambda d: d.update(goal_test="ball", final_goal_distance=0.001),
                      r"^final_goal_distance is recorded as 0\.001, but the path ends [\d.]+ "
                      r"from the goal \(distance to the goal\)$"),
    "bad goal test": (_set("goal_test", "sphere"),
                      r"^goal_test must be one of ball, system, function, got 'sphere'$"),
    "a path too long to re-simulate": (_set("path.1.duration", 1e6),
                                       r"^the path lasts \d+ steps of dt = 0\.01, more than "
                                       r"the 10000000 a check re-simulates$"),
    "path cost": (_set("path_cost", lambda v: v - 1.0),
                  r"^path_cost is recorded as [\d.]+, the re-simulated path gives [\d.]+$"),
    "path duration": (_set("path_duration", lambda v: v + 0.01),
                      r"^path_duration is recorded as"),
    "plan max |u|": (_set("max_abs_u", 0.9), r"^max_abs_u is recorded as 0\.9,"),
    "edge max |u|": (_set("path.ext.max_abs_u", 0.1),
                     r"^path\[{ext}\]\.max_abs_u is recorded as 0\.1, the re-simulated edge "
                     r"reaches \|u\| = "),
    "obstacle on the path": (_set("obstacles", [{"type": "box", "low": [-4.0, -10.0],
                                                 "high": [4.0, 10.0]}]),
                             r"^path\[0\]: the state \[.*\] at t = 0\.01 s lies in a recorded "
                             r"obstacle$"),
    "state constraint": (_set("config.plan.state_high", [100.0, 0.5]),
                         r"^path\[\d+\]: the state \[.*\] at t = [\d.]+ s leaves the state "
                         r"constraints of the recorded configuration$"),
    # malformed fields
    "costate of the wrong length": (_set("path.ext.costate", [1.0]),
                                    r"^path\[{ext}\]\.costate must be a list of 2 numbers "
                                    r"\(lambda_theta, lambda_omega\), got \[1\.0\]$"),
    "costate a string": (_set("path.ext.costate", "0 1"),
                         r"^path\[{ext}\]\.costate must be a list of 2 numbers"),
    "params missing": (_set("path.ext.params", None),
                       r"^path\[{ext}\]\.params must be a list of 1 number \(phi\), got None$"),
    "control of the wrong length": (_set("path.ctl.control", [0.5, 0.5]),
                                    r"^path\[{ctl}\]\.control must be a list of 1 number "
                                    r"\(torque\), got \[0\.5, 0\.5\]$"),
    "control NaN": (_set("path.ctl.control", [math.nan]),
                    r"^path\[{ctl}\]\.control must be finite"),
    "both kinds": (_set("path.ctl.costate", [0.0, 0.0]),
                   r"^path\[{ctl}\] has both a control and a costate"),
    "neither kind": (_set("path.ext.costate", None),
                     r"^path\[{ext}\] has neither a costate \(an extremal\) nor a control"),
    "duration a string": (_set("path.1.duration", "0.5"),
                          r"^path\[1\]\.duration must be a number, got '0\.5'$"),
    "infinite cost": (_set("path.1.cost", math.inf),
                      r"^path\[1\]\.cost must be finite, got inf$"),
    "missing path": (_delete("path"), r"^the plan has no 'path' field$"),
    "path not a list": (_set("path", {"0": 1}), r"^path must be a list of edges"),
    "edge not an object": (_set("path.1", [0, 1]), r"^path\[1\] must be an edge"),
    "edge without to": (_delete("path.1.to"), r"^path\[1\] has no 'to' field$"),
    "start of the wrong length": (_set("start", [0.0]),
                                  r"^start must be a list of 2 numbers \(theta, omega\)"),
    "goal NaN": (_set("goal", [math.nan, 0.0]), r"^goal must be finite"),
    "zero tolerance": (_set("goal_tolerance", 0), r"^goal_tolerance must be positive, got 0$"),
    "negative dt": (_set("dt", -0.01), r"^dt must be positive"),
    "unknown status": (_set("status", "done"), r"^status must be one of exact, approximate, "
                                               r"timeout, got 'done'$"),
    "solved but approximate": (_set("status", "approximate"),
                               r"^solved is True but status is 'approximate'$"),
    "bad input box": (_set("input_high", [-2.0]), r"^input_low \[-1\.0\] must lie below "
                                                  r"input_high \[-2\.0\]$"),
    "bad goal angles": (_set("goal_angles", [1]), r"^goal_angles must be \[\] or the "
                                                  r"system's angle coordinates \[0\]"),
    "bad obstacle": (_set("obstacles", [{"type": "circle"}]),
                     r"^obstacles: unknown obstacle type 'circle'"),
}


@pytest.mark.parametrize("name", list(TAMPERS))
def test_every_tampering_is_a_one_line_error(plan_file, tmp_path, name):
    edit, pattern = TAMPERS[name]
    d = _tampered(plan_file, tmp_path, edit)
    pattern = pattern.replace("{ext}", str(_ext_index(plan_file))) \
        .replace("{ctl}", str(_ctl_index(plan_file)))
    with pytest.raises(PlanCheckError) as info:
        _check(d)
    message = str(info.value)
    assert "\n" not in message
    assert isinstance(info.value, ValueError) and isinstance(info.value, ArtefactError)
    assert re.search(pattern, message), message


def test_the_tolerance_is_rounding_level(plan_file, tmp_path):
    # a change far below it passes, one far above it fails
    k = _ext_index(plan_file)
    d = _tampered(plan_file, tmp_path, _shift(f"path.{k}.to", 0, 1e-13))
    assert _check(d)["max_gap"] == pytest.approx(1e-13, rel=0.1)
    d = _tampered(plan_file, tmp_path, _shift(f"path.{k}.to", 0, 1e-7))
    with pytest.raises(PlanCheckError, match="1e-07 from its recorded to"):
        _check(d)
    d = _tampered(plan_file, tmp_path, _shift(f"path.{k}.to", 0, 1e-7))
    assert _check(d, rtol=1e-6)["max_gap"] == pytest.approx(1e-7, rel=1e-3)
