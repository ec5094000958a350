"""Trajectory export: samples along a plan's path, re-simulated, as a library call and a
command."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tests.conftest import pendulum_edge
from tests.test_cli import assert_one_line_error, invoke, tiny_run  # noqa: F401

from rrtcolearn import pipeline
from rrtcolearn.evaluate import sample_path


@pytest.fixture(scope="module")
def plan_dict(paper_model):
    p = pipeline.plan(paper_model, [-np.pi, 0], [0, 0], 0.1, seed=0, time_limit=None,
                      max_iterations=20_000)
    assert p.solved
    return json.loads(json.dumps(p.to_dict()))  # as a plan file holds it


def test_samples_follow_the_edges(paper_model, plan_dict):
    s = sample_path(paper_model.system, plan_dict)
    d = plan_dict
    steps = sum(round(e["duration"] / d["dt"]) for e in d["path"])
    # every step's sample, and both sides of each join of two edges (two rows, one time)
    assert len(s["t"]) == steps + len(d["path"])
    gaps = np.diff(s["t"])
    assert np.count_nonzero(gaps == 0) == len(d["path"]) - 1
    np.testing.assert_allclose(gaps[gaps > 0], d["dt"])
    np.testing.assert_allclose(s["state"][0], d["start"])
    np.testing.assert_allclose(s["state"][-1], d["path"][-1]["to"], atol=1e-9)
    # each edge's samples run from its stored node to its end along an independent RK4
    first = 0
    for i, e in enumerate(d["path"]):
        rows = np.flatnonzero(s["edge"] == i)
        assert rows[0] == first
        states, u, _ = pendulum_edge(e, d["time_weight"], d["dt"])
        np.testing.assert_allclose(s["state"][rows], states, atol=1e-9)
        np.testing.assert_allclose(s["input"][rows, 0], u, atol=1e-9)
        np.testing.assert_allclose(s["costate"][rows[0]], e["costate"])
        first = rows[-1] + 1


def test_coarser_step_is_every_kth_sample(paper_model, plan_dict):
    fine = sample_path(paper_model.system, plan_dict)
    coarse = sample_path(paper_model.system, plan_dict, dt=0.05)
    # every 5th step of the path's time, and each edge's first and last sample
    steps = np.rint(fine["t"] / plan_dict["dt"]).astype(int)
    ends = np.r_[True, np.diff(fine["edge"]) != 0] | np.r_[np.diff(fine["edge"]) != 0, True]
    keep = (steps % 5 == 0) | ends
    np.testing.assert_array_equal(coarse["state"], fine["state"][keep])
    np.testing.assert_array_equal(coarse["edge"], fine["edge"][keep])
    with pytest.raises(ValueError, match="whole multiple or a whole fraction"):
        sample_path(paper_model.system, plan_dict, dt=0.015)


def test_finer_step_re_simulates_each_edge_at_that_step(paper_model, plan_dict):
    """dt = step / 4: every edge integrated at the finer step by an RK4 written here, from
    its stored node; the samples at the plan's own times agree with the plan's step's to the
    integrators' difference, and the edges still end on the plan's nodes."""
    step, w = plan_dict["dt"], plan_dict["time_weight"]
    fine = sample_path(paper_model.system, plan_dict, dt=step / 4)
    coarse = sample_path(paper_model.system, plan_dict)
    gaps = np.diff(fine["t"])
    np.testing.assert_allclose(gaps[gaps > 0], step / 4)
    for i, e in enumerate(plan_dict["path"]):
        rows = np.flatnonzero(fine["edge"] == i)
        states, u, _ = pendulum_edge(e, w, step / 4)
        np.testing.assert_allclose(fine["state"][rows], states, atol=1e-9)
        np.testing.assert_allclose(fine["input"][rows, 0], u, atol=1e-9)
        np.testing.assert_allclose(fine["state"][rows[-1]], e["to"], atol=1e-6)
        np.testing.assert_allclose(fine["state"][rows[::4]],
                                   coarse["state"][coarse["edge"] == i], atol=1e-6)


def test_export_command_writes_csv_and_npz(tiny_run):  # noqa: F811
    plan_file = tiny_run / "plan.json"
    d = json.loads(plan_file.read_text())
    assert d["path"], "the tiny run's plan has a path to export"
    result = invoke("export", str(plan_file), "--dt", "0.02")
    assert result.exit_code == 0, result.output
    lines = [line for line in (tiny_run / "plan.csv").read_text().splitlines()
             if not line.startswith("#")]  # the header says what the columns hold
    assert lines[0] == "t,theta,omega,torque,lambda_theta,lambda_omega,edge"
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    np.testing.assert_allclose(rows[0, 1:3], d["start"])
    np.testing.assert_allclose(rows[-1, 1:3], d["path"][-1]["to"], atol=1e-9)
    out = tiny_run / "samples.npz"
    result = invoke("export", str(plan_file), "--format", "npz", "--out", str(out))
    assert result.exit_code == 0, result.output
    with np.load(out, allow_pickle=False) as z:
        np.testing.assert_allclose(z["state"][-1], d["path"][-1]["to"], atol=1e-9)
        assert str(z["columns"][0]) == "t"


def test_export_bad_input_is_one_line(tiny_run, tmp_path):  # noqa: F811
    plan_file = tiny_run / "plan.json"
    assert_one_line_error(invoke("export", str(plan_file), "--format", "xml"), 2, "csv or npz")
    assert_one_line_error(invoke("export", str(plan_file), "--dt", "-1"), 2, "positive")
    assert_one_line_error(invoke("export", str(tmp_path / "none.json")), contains="")


def test_export_refuses_a_plan_that_is_not_what_it_claims(tiny_run, tmp_path):  # noqa: F811
    """A file whose checksum was recomputed after an edit passes the checksum, not the
    check: an edge's end moved is a one-line error naming the edge, and nothing is written."""
    from rrtcolearn.data.store import write_checked_json

    d = json.loads((tiny_run / "plan.json").read_text())
    assert d["path"], "the tiny run's plan has a path"
    d.pop("sha256", None)
    d["path"][0]["to"][0] += 0.5
    edited = tmp_path / "edited.json"
    write_checked_json(edited, d)
    assert_one_line_error(invoke("export", str(edited)), 2, "path[0]")
    assert not edited.with_suffix(".csv").exists()
