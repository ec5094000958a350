"""The documentation's code as written: the configuration page's block equals the defaults,
the systems page's cart-pole is the example's, and the library snippets plan. (The README's
shell commands: tests/test_readme_commands.py.)"""

import re
import tomllib
from pathlib import Path

from rrtcolearn.config import Config, validate

ROOT = Path(__file__).parents[1]


def test_configuration_page_block_is_valid_and_matches_the_defaults():
    text = (ROOT / "docs" / "configuration.md").read_text()
    block = re.search(r"## The default configuration\n.*?```toml\n(.*?)```", text, re.S).group(1)
    documented = validate(tomllib.loads(block))
    assert documented == Config()


def test_systems_page_external_problem_block_defines_the_examples_dynamics():
    import numpy as np
    from examples.sparse_rrt_cartpole import make_cartpole

    text = (ROOT / "docs" / "systems.md").read_text()
    block = re.search(r"whole user\ncode for sparse_rrt's cart-pole.*?```python\n(.*?)```",
                      text, re.S).group(1)
    definition = block.split("register(")[0]  # the system only: no pipeline run here
    namespace: dict = {}
    exec(compile(definition, "docs/systems.md", "exec"), namespace)
    mine, theirs = namespace["make_cartpole"](), make_cartpole()
    rng = np.random.default_rng(0)
    x = rng.uniform(theirs.state_low, theirs.state_high, (200, 4))
    u = rng.uniform(-300, 300, (200, 1))
    np.testing.assert_allclose(mine.dynamics(x, u), theirs.dynamics(x, u), rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_array_equal(mine.input_limits(), theirs.input_limits())
    assert mine.defaults["config"] == theirs.defaults["config"]


def test_library_snippets_run_as_written(tmp_path, monkeypatch, capsys):
    """The README's "Using the library" block and docs/method.md's "The pieces, one by one",
    verbatim, in a fresh directory (each plans the swing-up; about 10 s each, most of it the
    40 000 simulations)."""
    readme = (ROOT / "README.md").read_text()
    section = re.search(r"## Using the library\n(.*?)\n## ", readme, re.S).group(1)
    method = (ROOT / "docs" / "method.md").read_text()
    pieces = re.search(r"## The pieces, one by one\n(.*?)(?:\n## |\Z)", method, re.S).group(1)
    blocks = [*re.findall(r"```python\n(.*?)```", section, re.S),
              *re.findall(r"```python\n(.*?)```", pieces, re.S)]
    assert len(blocks) == 2
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        exec(compile(block, "docs", "exec"), {})
        status = capsys.readouterr().out.split()[0]
        assert status == "exact"
