"""Property-based tests: random and malformed configs, states, files and command lines.

Every entry point must either accept an input that is valid, or refuse it with the project's
own one-line error; never a traceback, never an accepted invalid input.
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from rrtcolearn.cli import app
from rrtcolearn.config import Config, load_config, parse_obstacle, validate
from rrtcolearn.data.store import load_arrays, load_dataset, save_dataset, write_checked_json
from rrtcolearn.errors import ArtefactError, ConfigError, RRTCoLearnError
from rrtcolearn.pipeline import read_plan
from rrtcolearn.planning.problem import PlanningProblem, ProblemError
from rrtcolearn.systems import make

PENDULUM = make("pendulum")
KEYS = ["name", "seed", "system.name", "system.time_weight", "system.u_max",
        "generate.n_simulations", "generate.dt", "generate.max_cost", "generate.chunk_size",
        "clean.d", "clean.k_max", "clean.method", "learn.n_neighbors",
        "learn.validity_threshold", "plan.start", "plan.goal", "plan.goal_tolerance",
        "plan.goal_bias", "plan.obstacles", "experiment.epochs", "generate.n_simulation",
        "plan.tolerance", "nonsense", "plan", "system.name.x"]
scalars = st.one_of(st.integers(-10**12, 10**12), st.floats(allow_nan=True),
                    st.text(max_size=8), st.booleans(), st.none())
values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=6)
toml_values = st.one_of(
    st.sampled_from(["1", "-1", "0", "0.5", "nan", "inf", "-inf", "'x'", "[1, 2]",
                     "[nan, 0]", "[-3.14, 0]", "true", "1e400", "{a=1}", "[", "\"", "",
                     "[{type='box', low=[0,0], high=[1,1]}]", "[{type='circle'}]",
                     "'randomized'", "'greedy'", "'fast'"]),
    st.text(max_size=12))


def check_config_invariants(cfg: Config) -> None:
    """What an accepted configuration must satisfy."""
    validate(cfg.model_dump())  # round trip: still valid
    for section in (cfg.system, cfg.generate, cfg.clean, cfg.learn, cfg.plan):
        for value in section.model_dump().values():
            if isinstance(value, float):
                assert math.isfinite(value)
    assert cfg.system.time_weight > 0
    assert cfg.generate.n_simulations is None or cfg.generate.n_simulations >= 1
    assert cfg.clean.d > 0 and cfg.plan.goal_tolerance > 0


@given(st.lists(st.tuples(st.sampled_from(KEYS) | st.text(max_size=10), toml_values),
                max_size=4))
def test_set_overrides(pairs):
    overrides = [f"{k}={v}" for k, v in pairs]
    try:
        cfg = load_config(overrides=overrides)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    check_config_invariants(cfg)


@given(st.dictionaries(st.sampled_from(["name", "seed", "system", "generate", "clean",
                                        "learn", "plan", "experiment", "bogus"]),
                       values, max_size=4))
def test_config_documents(data):
    try:
        cfg = validate(data)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    check_config_invariants(cfg)


@given(st.text(max_size=30))
def test_obstacle_specs(spec):
    try:
        ob = parse_obstacle(spec)
    except ConfigError:
        return
    assert ob["type"] in ("box", "halfplane")


state_like = st.one_of(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.lists(st.one_of(st.text(max_size=3), st.none(), st.integers()), max_size=3),
    scalars)


@given(state_like, state_like, scalars, st.one_of(st.none(), st.floats()))
def test_planning_queries(start, goal, tol, u_max):
    try:
        p = PlanningProblem.create(PENDULUM, start, goal, tol, u_max=u_max)
    except ProblemError as exc:
        assert "\n" not in str(exc)
        return
    for x in (p.start, p.goal):
        assert x.shape == (2,) and np.all(np.isfinite(x))
        assert np.all(x >= PENDULUM.state_low) and np.all(x <= PENDULUM.state_high)
    assert math.isfinite(p.goal_tolerance) and p.goal_tolerance > 0
    assert p.u_max is None or (math.isfinite(p.u_max) and p.u_max > 0)


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory, small_dataset) -> bytes:
    path = tmp_path_factory.mktemp("f") / "d.npz"
    save_dataset(path, small_dataset.take(slice(0, 200)), {"system": "pendulum"})
    return path.read_bytes()


damages = st.one_of(
    st.tuples(st.just("flip"), st.lists(st.tuples(st.integers(0, 2**31), st.integers(1, 255)),
                                        min_size=1, max_size=4)),
    st.tuples(st.just("truncate"), st.integers(0, 2**31)),
    st.tuples(st.just("garbage"), st.binary(max_size=300)),
    st.tuples(st.just("append"), st.binary(min_size=1, max_size=50)))


def damaged(raw: bytes, damage: tuple) -> bytes:
    """``raw`` damaged as ``damage`` says; offsets are taken modulo the file's length."""
    kind, arg = damage
    b = bytearray(raw)
    if kind == "flip":
        for i, x in arg:
            b[i % len(b)] ^= x
    elif kind == "truncate":
        del b[arg % len(b):]
    elif kind == "garbage":
        b = bytearray(arg)
    else:
        b += arg
    return bytes(b)


# kept examples: nothing, a bare zip signature, an empty zip; the encrypted-flag and .npy
# header damages found by the fuzzing are tests in test_store.py (their offsets are computed)
@given(damages)
@example(("garbage", b""))
@example(("garbage", b"PK\x03\x04"))
@example(("garbage", b"PK\x05\x06" + bytes(18)))
@example(("truncate", 0))
def test_damaged_dataset_files(tmp_path_factory, valid_file, damage):
    path = tmp_path_factory.mktemp("g") / "d.npz"
    path.write_bytes(damaged(valid_file, damage))
    try:
        load_dataset(path)
    except ArtefactError as exc:
        assert "\n" not in str(exc)
        return
    # accepted: then it is the original content, byte for byte in every array
    original, _ = load_arrays(_write(tmp_path_factory, valid_file), "rrtcolearn.dataset")
    again, _ = load_arrays(path, "rrtcolearn.dataset")
    assert all(np.array_equal(original[k], again[k]) for k in original)


def _write(factory, raw: bytes) -> Path:
    path = factory.mktemp("o") / "d.npz"
    path.write_bytes(raw)
    return path


json_scalars = st.one_of(st.integers(-10**12, 10**12), st.floats(allow_nan=False,
                                                                 allow_infinity=False),
                         st.text(max_size=8), st.booleans(), st.none())
json_values = st.recursive(json_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=6)


@given(st.dictionaries(st.text(max_size=8), json_values, max_size=5), st.booleans())
def test_plan_and_model_json(tmp_path_factory, content, sign):
    path = tmp_path_factory.mktemp("j") / "plan.json"
    doc = {"format": "rrtcolearn.plan", "schema_version": 1, **content}
    if sign:
        write_checked_json(path, doc)
        original = json.loads(path.read_text())
        try:
            assert read_plan(path) == original
        except ArtefactError:  # only when the random keys overwrote format or version
            assert any(k in content for k in ("format", "schema_version", "sha256"))
    else:
        path.write_text(json.dumps(doc, default=str))
        with pytest.raises(ArtefactError):
            read_plan(path)


def test_pickle_payload_inside_npz_is_refused(tmp_path):
    buf = io.BytesIO()
    arr = np.empty(1, dtype=object)
    arr[0] = {"x": 1}
    np.save(buf, arr, allow_pickle=True)
    with zipfile.ZipFile(tmp_path / "p.npz", "w") as z:
        z.writestr("point_x1.npy", buf.getvalue())
    with pytest.raises(ArtefactError, match="unpickling"):
        load_dataset(tmp_path / "p.npz")


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("m") / "run"
    result = CliRunner().invoke(app, ["run", "--out", str(out), "--set",
                                      "generate.n_simulations=1500", "--set",
                                      "plan.max_iterations=5"])
    assert result.exit_code == 0, result.output
    return out


arg_values = st.one_of(st.sampled_from(["-3.14,0", "0,0", "nan,0", "1,a", "", "0", "1e9,0",
                                        "-1", "0.1", "inf", "box:-1,-1,1,1", "box:1",
                                        "halfplane:0,1,2"]), st.text(max_size=10))


@given(st.lists(st.tuples(st.sampled_from(["--start", "--goal", "--goal-tolerance",
                                           "--u-max", "--obstacle", "--seed",
                                           "--max-iterations", "--set", "--bogus"]),
                          arg_values), max_size=4))
def test_plan_command_line(tiny_model, tmp_path_factory, args):
    out = tmp_path_factory.mktemp("p") / "plan.json"
    argv = ["plan", "--model", str(tiny_model), "--out", str(out)]
    for flag, value in args:
        argv.append(f"{flag}={value}")
    argv += ["--max-iterations=3"]
    result = CliRunner().invoke(app, argv)
    text = result.output
    assert "Traceback" not in text
    assert result.exit_code in (0, 2), text
    if result.exit_code == 0:
        assert read_plan(out)["iterations"] <= 3
    else:
        assert not out.exists()
        assert isinstance(result.exception, SystemExit)


def test_errors_are_project_errors():
    assert issubclass(ProblemError, RRTCoLearnError)
    assert issubclass(ConfigError, RRTCoLearnError)


SAFE = ["--set", "generate.n_simulations=30", "--set", "generate.chunk_size=10",
        "--set", "generate.max_duration=0.5", "--set", "plan.max_iterations=3",
        "--set", "clean.k_max=50"]


@settings(max_examples=settings.default.max_examples // 4)  # a CLI run per example
@given(st.sampled_from(["generate", "clean", "fit", "run", "inspect", "systems"]),
       st.lists(st.tuples(st.sampled_from(["--seed", "--set", "--config", "--u-max",
                                           "--workers", "--obstacle", "--bogus"]),
                          st.one_of(toml_values, st.sampled_from(
                              ["system.u_max=2", "clean.method='greedy'", "seed=3",
                               "learn.n_neighbors=1", "/nonexistent.toml", "2", "-5"]))),
                max_size=3))
@example("generate", [("--config", "\x1e0")])  # found: a control character in an error message
@example("clean", [("--bogus", "1")])  # click's usage errors were several lines
@example("generate", [("--seed", "x")])
def test_every_command_line(tmp_path_factory, command, args):
    out = tmp_path_factory.mktemp("c") / "run"
    argv = [command]
    if command == "inspect":
        argv.append(str(out))
    elif command != "systems":
        argv += ["--out", str(out)]
        for flag, value in args:
            if flag == "--workers" and value not in ("1", "2"):
                value = "0"  # never start a large pool: 0 is refused, 1 and 2 are fine
            argv.append(f"{flag}={value}")
        argv += SAFE if command in ("generate", "run") else []
    result = CliRunner().invoke(app, argv)
    assert "Traceback" not in result.output
    assert result.exit_code in (0, 2), result.output
    if result.exit_code == 2:
        assert len(result.output.strip().splitlines()) == 1, result.output
    elif command in ("generate", "run"):
        from rrtcolearn.config import read_toml

        check_config_invariants(validate(read_toml(out / "config.toml")))
