"""Build records: a shipped system rebuilt from its generated module without sympy is the
system its sympy definition builds, and a record that does not match is never used."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from tests.test_startup import imported_after

from rrtcolearn.systems import _double_integrator, build_record
from rrtcolearn.systems.pendulum import make_pendulum
from rrtcolearn.systems.symbolic import with_input_limits

DEFINITIONS = {"pendulum": make_pendulum, "double_integrator": _double_integrator}


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RRTCOLEARN_CACHE", str(tmp_path))
    return tmp_path / "systems"


def records(cache) -> list:
    return sorted(cache.glob("rrtcolearn_build_*.json"))


@pytest.mark.parametrize("name", sorted(DEFINITIONS))
def test_a_record_rebuilds_the_system_its_definition_builds(name, cache):
    definition = DEFINITIONS[name]
    built = build_record.build(definition)
    assert built.derivation is not None and len(records(cache)) == 1
    again = build_record.build(definition)
    assert again.derivation is None and again.parametrisation is None
    assert again.definition is definition
    assert build_record._same(built, again) and again.source == built.source
    assert again.params_from_costate is built.params_from_costate
    # derived on demand, equal to the build's
    der, cp = again.symbolic()
    assert der == built.derivation and (cp is None) == (built.parametrisation is None)
    x = (0.4 * built.state_low + 0.6 * built.state_high)[None]
    p = (0.3 * built.param_low + 0.7 * built.param_high)[None]
    for a, b in zip(built.costate_from_params(x, p, 1.0), again.costate_from_params(x, p, 1.0),
                    strict=True):
        np.testing.assert_array_equal(a, b)


def test_make_uses_records_for_the_shipped_systems_only(cache, monkeypatch):
    from rrtcolearn import systems

    systems.make("pendulum")
    assert systems.make("pendulum").derivation is None and len(records(cache)) == 1
    # a user's definition may depend on anything: always built
    monkeypatch.setitem(systems._REGISTRY, "users_pendulum", lambda: make_pendulum())
    assert systems.make("users_pendulum").derivation is not None
    assert len(records(cache)) == 1


def test_an_edited_source_or_another_sympy_misses_the_record(cache, tmp_path, monkeypatch):
    build_record.build(make_pendulum)
    assert build_record.build(make_pendulum).derivation is None
    edited = tmp_path / "edited.py"
    edited.write_text("# an edit to the definition or the code generation\n")
    files = build_record._key_files()
    monkeypatch.setattr(build_record, "_key_files", lambda: [*files, edited])
    assert build_record.build(make_pendulum).derivation is not None
    monkeypatch.setattr(build_record, "_key_files", lambda: files)
    monkeypatch.setattr(build_record, "version", lambda package: "0.0")
    assert build_record.build(make_pendulum).derivation is not None
    assert len(records(cache)) == 3  # one per key: none was overwritten by another


def test_a_tampered_module_or_record_is_not_used(cache):
    built = build_record.build(make_pendulum)
    [record] = records(cache)
    module = cache / f"rrtcolearn_sys_{json.loads(record.read_text())['module']}.py"
    module.write_text(built.source.replace("N_STATES = 2", "N_STATES = 3"))
    assert build_record.build(make_pendulum).derivation is not None
    assert module.read_text() == built.source  # the build wrote it back
    assert build_record.build(make_pendulum).derivation is None
    for damage in ("{", json.dumps({"format": "other"}), "[]"):
        record.write_text(damage)
        assert build_record.build(make_pendulum).derivation is not None
        assert build_record.build(make_pendulum).derivation is None  # recorded again


def test_no_record_for_what_does_not_round_trip(cache):
    built = make_pendulum()
    fields = {f: getattr(built, f) for f in built.__dataclass_fields__}
    assert build_record._encode(built.__class__(**fields)) is not None
    for odd in ({"defaults": {"goal_fn": np.sin}}, {"angle_dims": (0.5 + 0j,)},
                {"state_low": built.state_low.astype(np.float32)}):
        assert build_record._encode(built.__class__(**{**fields, **odd})) is None, odd


def test_input_limits_on_a_recorded_system(cache):
    built = build_record.build(make_pendulum)
    again = build_record.build(make_pendulum)
    limited = with_input_limits(again, -2.0, 2.0)
    assert limited.source == with_input_limits(built, -2.0, 2.0).source
    assert limited.parametrisation is not None  # the pendulum's phi, not the default
    assert with_input_limits(limited, None, None).source == built.source


def test_a_recorded_system_pickles_for_workers(cache):
    build_record.build(make_pendulum)
    again = build_record.build(make_pendulum)
    copy = pickle.loads(pickle.dumps(again))
    assert copy.source == again.source and copy.definition is make_pendulum
    assert copy.costate_from_params is again.costate_from_params


def test_a_system_with_configured_limits_has_a_record_of_its_own(cache):
    limits = ([-2.0], [2.0])
    built = build_record.build(make_pendulum, limits)
    again = build_record.build(make_pendulum, limits)
    assert built.derivation is not None and again.derivation is None
    assert build_record._same(built, again) and len(records(cache)) == 1
    assert again.source == with_input_limits(make_pendulum(), -2.0, 2.0).source
    der, cp = again.symbolic()  # the limited derivation, with the pendulum's phi
    assert der.input_high == (2.0,) and cp is not None
    assert with_input_limits(again, None, None).source == make_pendulum().source
    assert build_record.build(make_pendulum, ([-1.0], [1.0])).derivation is not None


def test_configured_limits_need_no_sympy_in_a_later_process(cache):
    """`plan` on a model with input limits builds its system from a record too."""
    code = ("from rrtcolearn.config import Config\n"
            "from rrtcolearn.pipeline import system_from_config\n"
            "c = Config()\n"
            "s = system_from_config(c.model_copy(update={'system': c.system.model_copy("
            "update={'u_max': 1.5})}))\n"
            "assert s.input_high.tolist() == [1.5]")
    env = {"RRTCOLEARN_CACHE": str(cache.parent)}
    assert "sympy" in imported_after(code, env)  # the first builds and records
    assert "sympy" not in imported_after(code, env)
