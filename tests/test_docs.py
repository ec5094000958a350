"""The README's configuration block is a valid configuration equal to the defaults."""

import re
import tomllib
from pathlib import Path

from rrtcolearn.config import Config, validate


def test_readme_configuration_block_is_valid_and_matches_the_defaults():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    block = re.search(r"## Configuration.*?```toml\n(.*?)```", text, re.S).group(1)
    documented = validate(tomllib.loads(block))
    assert documented == Config()


def test_readme_external_problem_block_defines_the_examples_dynamics():
    import numpy as np
    from examples.sparse_rrt_cartpole import make_cartpole

    text = (Path(__file__).parents[1] / "README.md").read_text()
    block = re.search(r"whole user\ncode for sparse_rrt's cart-pole.*?```python\n(.*?)```",
                      text, re.S).group(1)
    definition = block.split("register(")[0]  # the system only: no pipeline run here
    namespace: dict = {}
    exec(compile(definition, "README.md", "exec"), namespace)
    mine, theirs = namespace["make_cartpole"](), make_cartpole()
    rng = np.random.default_rng(0)
    x = rng.uniform(theirs.state_low, theirs.state_high, (200, 4))
    u = rng.uniform(-300, 300, (200, 1))
    np.testing.assert_allclose(mine.dynamics(x, u), theirs.dynamics(x, u), rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_array_equal(mine.input_limits(), theirs.input_limits())
    assert mine.defaults["config"] == theirs.defaults["config"]


def test_readme_library_blocks_run_as_written(tmp_path, monkeypatch, capsys):
    """"Using the library": both blocks, verbatim, in a fresh directory (each plans the
    swing-up; about 10 s each, most of it the 40 000 simulations)."""
    text = (Path(__file__).parents[1] / "README.md").read_text()
    section = re.search(r"## Using the library\n(.*?)\n### ", text, re.S).group(1)
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 2
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})
        status = capsys.readouterr().out.split()[0]
        assert status == "exact"
