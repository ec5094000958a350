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
