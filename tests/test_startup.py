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
