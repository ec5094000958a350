"""Start-up: the command line imports only what a command uses.

Checked in a fresh interpreter (``sys.modules``), not by timing: `bench/startup.py` measures
the times.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import rrtcolearn

SRC = str(Path(rrtcolearn.__file__).parents[1])
HEAVY = ("numpy", "numba", "scipy", "pydantic", "sympy", "matplotlib", "sklearn", "ompl",
         "casadi", "dask")


def imported_after(code: str, env: dict | None = None) -> list[str]:
    """The HEAVY top-level modules in ``sys.modules`` after running ``code`` in a fresh
    interpreter that imports this checkout's package."""
    probe = (f"import sys\n{code}\nimport json\n"
             f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))")
    env = {**os.environ, **(env or {}),
           "PYTHONPATH": os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          env=env, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_importing_the_cli_imports_no_library():
    assert imported_after("import rrtcolearn.cli") == []


def test_help_imports_no_library():
    code = ("import rrtcolearn.cli as c\nsys.argv = ['rrtcolearn', '--help']\n"
            "try:\n    c.main()\nexcept SystemExit:\n    pass")
    assert imported_after(code) == []


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    from typer.testing import CliRunner

    from rrtcolearn.cli import app

    out = tmp_path_factory.mktemp("startup") / "tiny"
    result = CliRunner().invoke(app, [
        "run", "--seed", "3", "--out", str(out), "--set", "generate.n_simulations=3000",
        "--set", "clean.k_max=500", "--set", "plan.max_iterations=200"])
    assert result.exit_code == 0, result.output
    return out


def test_plan_imports_neither_sympy_nor_matplotlib(tiny_model, tmp_path):
    from rrtcolearn.systems import build_record, make
    from rrtcolearn.systems.pendulum import make_pendulum

    make("pendulum")  # writes the pendulum's build record, where the cache is writable
    if make("pendulum").derivation is not None:
        pytest.skip("the system cache is not writable here: no build record")
    assert build_record.record_key(make_pendulum) is not None
    plan = ("import rrtcolearn.cli as c\n"
            f"sys.argv = ['rrtcolearn', 'plan', '--model', {str(tiny_model)!r}, "
            f"'--seed', '2', '--max-iterations', '100', '--out', "
            f"{str(tmp_path / 'p.json')!r}{{}}]\n"
            "try:\n    c.main()\nexcept SystemExit as e:\n    assert e.code == 0, e.code")
    used = imported_after(plan.format(""))
    assert "sympy" not in used and "matplotlib" not in used, used
    assert (tmp_path / "p.json").is_file() and not (tmp_path / "p.png").exists()
    assert "matplotlib" in imported_after(plan.format(", '--plot'"))
    assert (tmp_path / "p.png").is_file()


def test_load_model_loads_the_kernels_a_plan_calls(tiny_model):
    """In a fresh process, the first plans compile nothing and load nothing: every kernel
    signature they call was loaded with the model."""
    code = f"""
from rrtcolearn import pipeline
model = pipeline.load_model({str(tiny_model)!r})
kernels = ("costate_from_params_jit", "rollout_jit", "input_max_abs_jit", "propagate_jit",
           "rollout_batch_jit")
def signatures():
    return {{k: [str(s) for s in getattr(model.system, k).signatures] for k in kernels}}
loaded = signatures()
assert all(len(s) == 1 for s in loaded.values()), loaded
for seed, u_max in ((1, None), (2, 1.0)):
    pipeline.plan(model, [-3.0, 0.0], [0.0, 0.0], 0.3, seed, max_iterations=100, u_max=u_max)
assert signatures() == loaded, (signatures(), loaded)
"""
    assert imported_after(code) is not None  # raises on a failed assertion in the process


def test_plan_pauses_the_collector_for_its_start_up(tiny_model, tmp_path):
    """`plan` loads the model with the collector paused (two full passes over the imports'
    objects cost 0.1 s: docs/performance.md), plans with it running and the start-up's
    objects frozen, and in a process that goes on (the command called in-process) leaves it
    running with nothing frozen."""
    code = f"""
import gc
import rrtcolearn.cli as c
from rrtcolearn import pipeline
seen = []
load, plan = pipeline.load_model, pipeline.plan
def load_spy(*a, **k):
    seen.append(("load", gc.isenabled()))
    return load(*a, **k)
def plan_spy(*a, **k):
    seen.append(("plan", gc.isenabled(), gc.get_freeze_count() > 0))
    return plan(*a, **k)
pipeline.load_model, pipeline.plan = load_spy, plan_spy
sys.argv = ['rrtcolearn', 'plan', '--model', {str(tiny_model)!r}, '--seed', '2',
            '--max-iterations', '100', '--out', {str(tmp_path / 'p.json')!r}]
try:
    c.app()
except SystemExit as e:
    assert e.code == 0, e.code
assert seen == [("load", False), ("plan", True, True)], seen
assert gc.isenabled() and gc.get_freeze_count() == 0
"""
    assert imported_after(code) is not None  # raises on a failed assertion in the process
    assert (tmp_path / "p.json").is_file()
