"""The documentation's code as written: the configuration page's block equals the defaults,
the systems page's cart-pole is the example's, and the library snippets plan. (The README's
shell commands: tests/test_readme_commands.py.)"""

import re
import tomllib
from pathlib import Path

import pytest

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


def _anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces to
    hyphens, repeats numbered."""
    seen: dict[str, int] = {}
    out = set()
    text = re.sub(r"```.*?```", "", markdown, flags=re.S)  # no headings inside code
    for heading in re.findall(r"^#{1,6} (.+)$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINKS = [(page, target) for page in PAGES
         for target in re.findall(r"\]\(([^)\s]+)\)",
                                  re.sub(r"```.*?```", "", page.read_text(), flags=re.S))
         if not re.match(r"[a-z]+:", target)]


def _param(page: Path, target: str):
    return pytest.param(page, target, id=f"{page.name}->{target}")


@pytest.mark.parametrize("page,target", [_param(*link) for link in LINKS])
def test_documentation_links_resolve_inside_the_repository(page, target):
    """Every relative link of the README and docs/ names a file of the repository, and an
    anchor a heading of it; no link leaves the repository."""
    path, _, anchor = target.partition("#")
    file = (page.parent / path).resolve() if path else page
    assert file.exists(), f"{page.name}: link to a missing {target}"
    assert ROOT in file.parents, f"{page.name}: link out of the repository {target}"
    if anchor:
        assert anchor in _anchors(file.read_text()), f"{page.name}: no heading #{anchor} in {path}"


def test_readme_has_no_commit_hash_date_or_outside_link():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    assert not re.findall(r"\b[0-9a-f]{7,40}\b", text)
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", text)
    assert not re.findall(r"\]\((?:https?:|/)", text)
    assert "this machine" not in text
