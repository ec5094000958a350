"""Query files (`rrtcolearn.queries`): parsing a new user's CSV and JSON lines, and the
output directory of a batch."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from rrtcolearn.errors import ConfigError
from rrtcolearn.queries import NOT_PLANNED, Query, plan_query_file, read_queries


def _read(tmp_path: Path, name: str, content: str | bytes, n: int | None = 2) -> list[Query]:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return read_queries(path, 0.1, n)


def _refused(tmp_path: Path, name: str, content: str, *contains: str) -> str:
    with pytest.raises(ConfigError) as info:
        _read(tmp_path, name, content)
    message = str(info.value)
    for text in contains:
        assert text in message, message
    return message


def test_a_byte_order_mark_is_accepted(tmp_path):
    bom = b"\xef\xbb\xbf"
    (q,) = _read(tmp_path, "q.csv", bom + b'start,goal,seed\n"-3,0","0,0",4\n')
    assert q == Query((-3.0, 0.0), (0.0, 0.0), 0.1, 4)
    (j,) = _read(tmp_path, "q.jsonl", bom + b'{"start": [-3, 0], "goal": [0, 0], "seed": 4}\n')
    assert j == q


@pytest.mark.parametrize("fields, contains", [
    ('"seed": 2.5', "seed must be a non-negative integer, got 2.5"),
    ('"seed": 2.0', "seed must be a non-negative integer, got 2.0"),  # refused: a float
    ('"seed": true', "seed must be a non-negative integer, got true"),
    ('"seed": -1', "seed must be a non-negative integer, got -1"),
    ('"seed": [1]', "seed must be a non-negative integer"),
    ('"goal_tolerance": true', "goal_tolerance must be a positive number, got true"),
    ('"goal_tolerance": 0', "goal_tolerance must be a positive number, got 0"),
    ('"goal_tolerance": NaN', "goal_tolerance must be a positive number"),
])
def test_json_numbers_are_checked_like_csv_cells(tmp_path, fields, contains):
    row = '{"start": [-3, 0], "goal": [0, 0], ' + fields + "}"
    _refused(tmp_path, "q.jsonl", "\n" + row + "\n", "q.jsonl, line 2: " + contains)


@pytest.mark.parametrize("row, contains", [
    ('{"start": [true, 0], "goal": [0, 0]}', "start must be a list of numbers, got [true, 0]"),
    ('{"start": [-3, 0], "goal": [0, false]}', "goal must be a list of numbers"),
])
def test_booleans_are_not_state_values(tmp_path, row, contains):
    _refused(tmp_path, "q.jsonl", row + "\n", "line 1: " + contains)


def test_integer_seeds_are_kept(tmp_path):
    qs = _read(tmp_path, "q.jsonl", '{"start": [-3, 0], "goal": [0, 0], "seed": 7}\n'
               '{"start": [-3, 0], "goal": [0, 0], "seed": "8"}\n')
    assert [q.seed for q in qs] == [7, 8]
    _refused(tmp_path, "q.csv", 'start,goal,seed\n"-3,0","0,0",2.7\n',
             "line 2: seed must be a non-negative integer, got '2.7'")
    _refused(tmp_path, "q.csv", 'start,goal,seed\n"-3,0","0,0",2.0\n', "got '2.0'")


def test_repeated_keys_and_columns_are_refused(tmp_path):
    _refused(tmp_path, "q.jsonl", '{"start": [-3, 0], "goal": [0, 0]}\n'
             '{"start": [-3, 0], "goal": [0, 0], "start": [-1, 0]}\n',
             "q.jsonl, line 2: the key 'start' appears twice")
    _refused(tmp_path, "q.csv", 'start,goal,start\n"-3,0","0,0","-1,0"\n',
             "q.csv, line 1: the header repeats the column 'start'")


def test_queries_know_their_file_lines(tmp_path):
    rows = ['{"start": [-3, 0], "goal": [0, 0]}', "", '{"start": [-2, 0], "goal": [0, 0]}',
            "  ", '{"start": [-1, 0], "goal": [0, 0], "seed": 9}']
    qs = _read(tmp_path, "q.jsonl", "\n".join(rows) + "\n")
    assert [q.line for q in qs] == [1, 3, 5]
    assert [q.seed for q in qs] == [0, 1, 9]  # no seed: the index among the queries
    qs = _read(tmp_path, "q.csv", 'start,goal\n"-3,0","0,0"\n\n"-2,0","0,0"\r\n')
    assert [q.line for q in qs] == [2, 4] and [q.seed for q in qs] == [0, 1]
    # an error names the same line a query would carry
    _refused(tmp_path, "q.jsonl", "\n".join([*rows[:4], '{"start": [0], "goal": [0, 0]}']),
             "q.jsonl, line 5: start needs 2 values")
    assert Query((0.0,), (0.0,), 0.1, 0).line is None  # made in code, not read from a file


def test_unquoted_csv_states_say_to_quote(tmp_path):
    message = _refused(tmp_path, "q.csv", "start,goal,goal_tolerance,seed\n-3.14,0,0,0\n",
                       "line 2: start needs 2 values (the system's states), got 1",
                       '"-3.14,0"')
    assert "goal_tolerance" not in message  # the states are checked before the tolerance
    # JSON lines have no quoting to blame; too many values have no hint either
    message = _refused(tmp_path, "q.jsonl", '{"start": [-3], "goal": [0, 0]}\n',
                       "start needs 2 values")
    assert "in CSV quote" not in message
    message = _refused(tmp_path, "q.csv", 'start,goal\n"-3,0,1","0,0"\n', "got 3")
    assert "in CSV quote" not in message


def test_an_output_directory_of_another_batch_is_refused(tmp_path):
    queries = [Query((-3.0, 0.0), (0.0, 0.0), 0.1, 0)]
    for name in ("plans.csv", "plan-00003.json"):
        out = tmp_path / name.replace(".", "_")
        out.mkdir()
        (out / name).write_text("mine\n")
        # refused before the model is loaded: the run directory does not even exist
        with pytest.raises(ConfigError, match="holds the results of another batch"):
            plan_query_file(tmp_path / "no-run", queries, out, config=None)
        assert [p.name for p in out.iterdir()] == [name]
        assert (out / name).read_text() == "mine\n"  # never deleted


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A small pendulum model's run directory (a few hundred simulations)."""
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    cfg = load_config(overrides=['system.name="pendulum"', "generate.n_simulations=300",
                                 "clean.k_max=100"])
    run = tmp_path_factory.mktemp("tiny")
    pipeline.generate(cfg, run)
    pipeline.clean(cfg, run)
    return run, pipeline.fit(cfg, run).config


def _summary(out: Path) -> list[dict]:
    return list(csv.DictReader((out / "plans.csv").open()))


def test_the_summary_says_which_plans_the_step_resolves(tiny_run, tmp_path):
    """plans.csv's ``resolved`` column is the plan file's own step check, so a batch's
    solved but unresolved plans can be told from the good ones."""
    run, cfg = tiny_run
    queries = [Query((-3.0 + k / 2, 0.0), (0.0, 0.0), 0.5, k) for k in range(4)]
    plan_query_file(run, queries, tmp_path, config=cfg, max_iterations=200)
    summary = _summary(tmp_path)
    assert any(r["solved"] == "True" for r in summary)
    for r in summary:
        plan = json.loads((tmp_path / r["file"]).read_text())
        assert r["resolved"] == str(plan["step_check"]["resolved"])


def test_a_batch_that_ends_early_leaves_its_summary(tiny_run, tmp_path, monkeypatch):
    run, cfg = tiny_run
    queries = [Query((-3.0 + k / 2, 0.0), (0.0, 0.0), 0.3, k) for k in range(4)]
    rows = plan_query_file(run, queries, tmp_path / "all", config=cfg, max_iterations=20)
    assert [r["status"] for r in _summary(tmp_path / "all")] == [r["status"] for r in rows]

    def interrupt(done: int) -> None:
        if done == 2:
            raise KeyboardInterrupt

    out = tmp_path / "interrupted"
    with pytest.raises(KeyboardInterrupt):
        plan_query_file(run, queries, out, config=cfg, max_iterations=20, progress=interrupt)
    summary = _summary(out)
    assert [r["query"] for r in summary] == ["0", "1", "2", "3"]
    assert [r["seed"] for r in summary] == ["0", "1", "2", "3"]
    assert [r["status"] for r in summary[2:]] == [NOT_PLANNED] * 2
    assert all(r["file"] == "" for r in summary[2:])
    assert [r["file"] for r in summary[:2]] == ["plan-00000.json", "plan-00001.json"]
    assert sorted(p.name for p in out.glob("plan-*.json")) == ["plan-00000.json",
                                                                "plan-00001.json"]
    # the planned rows are those of the full batch (the plans do not depend on the stop)
    drop = {"planning_cpu_s"}
    assert [{k: v for k, v in r.items() if k not in drop} for r in summary[:2]] == \
        [{k: v for k, v in r.items() if k not in drop} for r in _summary(tmp_path / "all")[:2]]

    # a failed write: the plans before it are summarised, and the write's error is raised
    from rrtcolearn.data import store

    written = store.write_checked_json

    def disk_full(path, obj):
        if path.name == "plan-00001.json":
            raise OSError(28, "No space left on device")
        written(path, obj)

    monkeypatch.setattr(store, "write_checked_json", disk_full)
    out = tmp_path / "full"
    with pytest.raises(OSError, match="No space"):
        plan_query_file(run, queries, out, config=cfg, max_iterations=20)
    assert [r["status"] != NOT_PLANNED for r in _summary(out)] == [True, False, False, False]
    assert json.loads((out / "plan-00000.json").read_text())["seed"] == 0
    # and the same directory is refused for the next try: it holds this batch's results
    with pytest.raises(ConfigError, match="another batch"):
        plan_query_file(run, queries, out, config=cfg, max_iterations=20)
