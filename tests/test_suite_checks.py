"""The suite's own guards (tests/conftest.py): a test skipped for a missing extra fails the run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

CONFTEST = Path(__file__).with_name("conftest.py")


def run_pytest(tmp_path: Path, body: str) -> subprocess.CompletedProcess:
    (tmp_path / "conftest.py").write_text(CONFTEST.read_text())
    (tmp_path / "test_probe.py").write_text(body)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-ra", "-p", "no:cacheprovider",
                           "--rootdir", str(tmp_path), str(tmp_path / "test_probe.py")],
                          capture_output=True, text=True, cwd=tmp_path, env=os.environ.copy(),
                          timeout=600)


def test_a_skip_for_a_missing_extra_fails_the_run(tmp_path):
    result = run_pytest(tmp_path, (
        "import pytest\n"
        "def test_needs_an_extra():\n"
        "    pytest.importorskip('an_extra_that_is_not_installed')\n"
        "def test_passes():\n"
        "    pass\n"))
    assert result.returncode == 1, result.stdout
    assert "skipped for a missing extra" in result.stdout
    assert "test_needs_an_extra" in result.stdout and "1 passed, 1 skipped" in result.stdout


def test_a_module_skipped_for_a_missing_extra_fails_the_run(tmp_path):
    result = run_pytest(tmp_path, "import pytest\npytest.importorskip('ompl_not_here')\n"
                                  "def test_x():\n    pass\n")
    assert result.returncode == 1, result.stdout
    assert "skipped for a missing extra" in result.stdout


def test_other_skips_do_not_fail_the_run(tmp_path):
    result = run_pytest(tmp_path, "import pytest\ndef test_x():\n    pytest.skip('not here')\n")
    assert result.returncode == 0, result.stdout
    assert "1 skipped" in result.stdout and "missing extra" not in result.stdout
