"""Datasets and models record the dynamics they were made for (`systems.base.dynamics_probe`),
and refuse a system of the same name whose dynamics or running cost differ: a definition
edited after a fit keeps its name, and its model would otherwise plan, silently, with
dynamics it never learned (a user's pendulum with another gravity planned with the old
model's steering: edge ends off by up to 0.8)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from tests.test_cli import assert_one_line_error, invoke

from rrtcolearn import pipeline
from rrtcolearn.config import load_config
from rrtcolearn.errors import ArtefactError
from rrtcolearn.pipeline.offline import _generation_key
from rrtcolearn.systems import make
from rrtcolearn.systems.base import dynamics_mismatch, dynamics_probe
from rrtcolearn.systems.pendulum import make_pendulum

ROOT = Path(__file__).parents[1]
HEAVIER = "tests.test_dynamics_record:heavier_pendulum"


def heavier_pendulum():
    """The paper's pendulum with a heavier bob: its name, other dynamics."""
    return make_pendulum({"m": 1.1})


def test_the_probe_holds_the_pendulums_dynamics_and_cost_by_hand():
    """f = (omega, sin theta + u) and H = w + l_th omega + l_om (sin theta + u) + u^2 / 2 at
    w = 1 (the paper's pendulum, by hand) at the recorded points, which lie in the boxes."""
    system = make("pendulum")
    probe = json.loads(json.dumps(dynamics_probe(system)))  # as a file holds it
    x, u, lam = (np.array(probe[k]) for k in ("x", "u", "costate"))
    assert len(x) >= 3 and np.all((x >= system.state_low) & (x <= system.state_high))
    assert np.all(np.abs(lam) <= 1) and np.ptp(x, axis=0).min() > 0  # distinct points
    th, om, v = x[:, 0], x[:, 1], u[:, 0]
    np.testing.assert_allclose(probe["f"], np.column_stack([om, np.sin(th) + v]), rtol=1e-13)
    h = 1.0 + lam[:, 0] * om + lam[:, 1] * (np.sin(th) + v) + 0.5 * v**2
    np.testing.assert_allclose(probe["H"], h, rtol=1e-13)
    assert dynamics_mismatch(system, probe) is None
    # the same definition built again (another object, another build path) matches
    assert dynamics_mismatch(make_pendulum(), probe) is None


def test_other_dynamics_or_cost_of_the_same_name_are_told_apart():
    system = make("pendulum")
    probe = dynamics_probe(system)
    heavy = heavier_pendulum()
    assert heavy.name == system.name
    assert "dynamics f(x, u) differ" in dynamics_mismatch(heavy, probe)
    h = system.hamiltonian
    dearer = dataclasses.replace(system, hamiltonian=lambda x, lam, u, w: h(x, lam, u, w)
                                 + 0.05 * u[:, 0] ** 2)  # another input weight R
    assert "running cost" in dynamics_mismatch(dearer, probe)
    assert "2 states and 1 inputs, the system has 4 and 1" in \
        dynamics_mismatch(make("cartpole"), probe)
    assert "unreadable" in dynamics_mismatch(system, {"x": "garbage"})
    # a rebuild's rounding is no difference, a change in the 8th digit is
    nudged = json.loads(json.dumps(probe))
    nudged["f"][0][1] *= 1 + 1e-12
    assert dynamics_mismatch(system, nudged) is None
    nudged["f"][0][1] *= 1 + 1e-8
    assert dynamics_mismatch(system, nudged) is not None


def test_edited_dynamics_are_new_data_and_a_refused_model(tmp_path, monkeypatch):
    """The generation key covers the dynamics (a rerun after an edit generates afresh
    instead of reusing the old dataset); cleaning, fitting and planning refuse files made
    for other dynamics with a one-line error, and accept the system they were made for."""
    monkeypatch.chdir(ROOT)
    cfg = load_config(overrides=['system.name="pendulum"', "generate.n_simulations=300",
                                 "clean.k_max=100"])
    heavy_cfg = load_config(overrides=[f'system.name="{HEAVIER}"',
                                       "generate.n_simulations=300", "clean.k_max=100"])
    assert _generation_key(cfg, make("pendulum")) != _generation_key(cfg, heavier_pendulum())
    run = tmp_path / "run"
    pipeline.generate(cfg, run)
    with pytest.raises(ArtefactError, match="made for other dynamics"):
        pipeline.clean(heavy_cfg, run)
    pipeline.clean(cfg, run)
    with pytest.raises(ArtefactError, match="made for other dynamics"):
        pipeline.fit(heavy_cfg, run)
    pipeline.fit(cfg, run)
    query = ["--start=-3.1,0", "--goal", "0,0", "--goal-tolerance", "0.3",
             "--set", "plan.max_iterations=50", "--out", str(tmp_path / "p.json")]
    result = invoke("plan", "--model", str(run), "--system", HEAVIER, *query)
    assert_one_line_error(result, contains="made for other dynamics")
    assert not (tmp_path / "p.json").exists()
    result = invoke("plan", "--model", str(run), "--system",
                    "rrtcolearn.systems.pendulum:make_pendulum", *query)
    assert result.exit_code == 0, result.output


def test_configured_limits_that_replace_the_definitions_are_shown():
    """A definition's own input limits replaced by configured ones (documented, but it was
    silent) are recorded with the derived settings, both boxes named; the same limits, or
    none configured, record nothing."""
    from rrtcolearn.pipeline.configure import replaced_limits

    spec = 'system.name="examples.sparse_rrt_cartpole:make_cartpole"'  # |F| <= 300
    wider = replaced_limits(load_config(overrides=[spec, "system.u_max=400"]))
    assert wider.key == "system.input_limits"
    assert wider.text == ("-400 <= force <= 400: configured: they replace the limits the "
                          "system's definition declares (-300 <= force <= 300)")
    assert replaced_limits(load_config(overrides=[spec, "system.u_max=300"])) is None
    assert replaced_limits(load_config(overrides=[spec])) is None
    # the pendulum declares none: a limit is the paper's u_max, nothing replaced
    assert replaced_limits(load_config(overrides=["system.u_max=1"])) is None
