"""The README's shell commands, run as written, in a fresh directory, in the order a reader
runs them; and its command-line synopsis against the command line itself.

What runs: every line of every ```bash block, the files the README says to save
("Save as `my_robot.py`:", "with `exp.toml`:" before a block) and the ```python blocks of
"Plan for your own robot". The ```python blocks of "Using the library" are run by
tests/test_docs.py; ```text blocks are synopses, checked option by option below.

A line runs with these substitutions and no others:
- `rrtcolearn` or `.venv/bin/rrtcolearn` at the start of a line -> this environment's entry
  point, `python` -> this interpreter;
- the budgets of BUDGETS appended to the commands that would take minutes (each with its
  reason): only the experiment, which is 20 minutes of CPU as written;
- `make X` is not run (it would build a new .venv, and `make test` is this suite): `make -n X`
  checks that the target exists, and `make run` is replaced by the command its recipe runs,
  `rrtcolearn run`;
- `. .venv/bin/activate` is not run: the entry point is called by its path instead.
Each line must exit with status 0; the files the README names as written are checked after.
The shell commands take about a minute (69 s wall, one measurement), most of it the two
`run`s (40 000 simulations each), plus compiling `my_robot`'s kernels the first time on a
machine; the synopsis and inline checks take under a second."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]
README = (ROOT / "README.md").read_text()
BIN = Path(sys.executable).parent

# appended to a command that starts with the key (after the entry point); why each is needed
BUDGETS = {
    # as written: 100 runs x 3 planners x 4 problems (KPIECE1's failures take 10 s each) on
    # three 40 000-simulation datasets, about 20 CPU minutes; here 1 run each of at most 2 s
    "experiment": ["--set", "experiment.runs_per_epoch=1", "--set", "experiment.time_limit=2.0",
                   "--set", "generate.n_simulations=4000"],
}


def _blocks(text: str) -> list[tuple[str, str, str]]:
    """(language, body, the line before the block) for every fenced block, in order."""
    out = []
    for m in re.finditer(r"```(\w*)\n(.*?)```", text, re.S):
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        out.append((m.group(1), m.group(2), before))
    return out


def _section(name: str) -> str:
    return re.search(rf"\n## {re.escape(name)}\n(.*?)(?=\n## |\Z)", README, re.S).group(1)


def _lines(body: str) -> list[str]:
    """The commands of a shell block: continuation lines joined, comments dropped."""
    body = body.replace("\\\n", " ")
    commands = []
    for line in body.splitlines():
        line = re.sub(r"\s{2,}#.*$", "", line).strip()  # a comment: two spaces, then #
        if line and not line.startswith("#"):
            commands.append(line)
    return commands


def _make_target(line: str) -> str:
    target = line.split()[1]
    dry = subprocess.run(["make", "-n", "-C", str(ROOT), target], capture_output=True,
                         text=True)
    assert dry.returncode == 0, f"README's `{line}`: no such make target ({dry.stderr})"
    return dry.stdout


def _as_run(line: str) -> str | None:
    """The line as this test runs it (None: not run, see the module docstring)."""
    if line.startswith(". .venv/bin/activate") or line.startswith("source .venv/bin/activate"):
        return None
    if line.startswith("make "):
        recipe = _make_target(line)
        if line.split()[1] != "run":
            return None
        assert ".venv/bin/rrtcolearn run" in recipe  # make run is `rrtcolearn run`
        line = "rrtcolearn run"
    words = line.split()
    if words[0] in ("rrtcolearn", ".venv/bin/rrtcolearn"):
        extra = BUDGETS.get(words[1], []) if len(words) > 1 else []
        return " ".join([str(BIN / "rrtcolearn"), *words[1:], *extra])
    if words[0] == "python":
        return " ".join([sys.executable, line[len("python"):]])
    raise AssertionError(f"README command {line!r}: this test does not know how to run it")


def test_readme_shell_commands_run_as_written(tmp_path):
    """Install and run, your own robot, the comparison with OMPL, development: every
    command, in order, in one fresh directory."""
    env = dict(os.environ, MPLBACKEND="Agg")
    ran = []
    robot = _section("Plan for your own robot: torque limits and obstacles")
    for lang, body, before in _blocks(README):
        saved = re.search(r"`([\w.]+)`:$", before)
        if saved and lang in ("python", "toml"):
            (tmp_path / saved.group(1)).write_text(body)
            continue
        if lang == "python" and body in robot:
            done = subprocess.run([sys.executable, "-c", body], cwd=tmp_path, env=env,
                                  capture_output=True, text=True)
            assert done.returncode == 0, f"README snippet failed:\n{body}\n{done.stderr}"
            assert done.stdout.split()[0] in ("exact", "approximate", "timeout")
            ran.append("python snippet")
            continue
        if lang not in ("bash", "sh"):
            continue
        for line in _lines(body):
            command = _as_run(line)
            if command is None:
                continue
            done = subprocess.run(command, shell=True, cwd=tmp_path, env=env,
                                  capture_output=True, text=True)
            assert done.returncode == 0, f"README's `{line}` failed:\n{done.stderr[-3000:]}"
            ran.append(line)
    assert len(ran) >= 8, ran
    # what the README says these commands write
    for path in ["runs/pendulum-swingup/plan.json", "runs/pendulum-swingup/plan.png",
                 "runs/swingup/plans.csv", "runs/my_robot/model.json",
                 "runs/my_robot/p1.json", "runs/my_robot/p1.png", "runs/my_robot/p1.csv",
                 "runs/ompl-comparison/report.md", "runs/ompl-comparison/runs.csv",
                 "runs/ompl-comparison/benchmark.db"]:
        assert (tmp_path / path).is_file(), f"{path} missing after the README's commands"
    queries = (tmp_path / "runs/swingup/plans.csv").read_text().splitlines()
    assert len(queries) == 101  # a header and the 100 seeds of swingup.jsonl


def _synopsis() -> dict[str, set[str]]:
    """Options per command in the README's synopsis (the ```text block of "The command
    line"); "" holds the options before the command."""
    block = next(body for lang, body, _ in _blocks(_section("The command line"))
                 if lang == "text")
    options: dict[str, set[str]] = {}
    command = None
    for line in block.splitlines():
        line = line.split("#")[0]
        m = re.match(r"rrtcolearn (\[[^\]]*\] )*(\w+|COMMAND)", line)
        if m:
            command = "" if m.group(2) == "COMMAND" else m.group(2)
            options.setdefault(command, set())
        options[command] |= set(re.findall(r"(?<![\w-])(--?[a-z][a-z-]*)", line))
    return options


def test_readme_synopsis_lists_every_option_of_every_command():
    """No option of the command line is missing from the README, and the README names
    none that does not exist."""
    import typer.main as typer_main

    from rrtcolearn.cli import app

    group = typer_main.get_command(app)
    actual = {name: {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)
                     if o.startswith("-")} - {"--help"}
              for name, cmd in group.commands.items()}
    actual[""] = {o for p in group.params for o in p.opts} - {"--help"}
    documented = _synopsis()
    assert documented.keys() == actual.keys()
    for name in actual:
        assert documented[name] == actual[name], (
            f"rrtcolearn {name}: missing from the README {actual[name] - documented[name]}, "
            f"not an option {documented[name] - actual[name]}")


def test_readme_inline_commands_use_existing_options():
    """Commands quoted in the README's prose (`rrtcolearn ...`) name a real command and
    real options of it."""
    import typer.main as typer_main

    from rrtcolearn.cli import app

    group = typer_main.get_command(app)
    quoted = re.findall(r"`rrtcolearn (\w+)([^`]*)`", README)
    assert quoted
    for name, rest in quoted:
        assert name in group.commands, f"`rrtcolearn {name}`: no such command"
        opts = {o for p in group.commands[name].params for o in (*p.opts, *p.secondary_opts)}
        for option in re.findall(r"(?<![\w-])(--[a-z][a-z-]*)", rest):
            assert option in opts, f"`rrtcolearn {name} ...{option}`: no such option"
