"""The commands that look without computing: systems (the registry) and inspect (a run
directory's artefacts and their digests)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rrtcolearn.cli.common import guard


def systems() -> None:
    """List the registered systems."""
    from rrtcolearn.systems import list_systems, make

    for name in list_systems():  # plain lines: rich would wrap them at its console width
        typer.echo(f"{name}: {make(name).description}")


def inspect(run_dir: Annotated[Path, typer.Argument(help="run directory")]) -> None:
    """Size and content digest (SHA-256) of every artefact of a run directory.

    Digests depend on content only (not on chunking, workers or file layout), so two labs can
    check that they hold the same dataset.
    """
    def body():
        from rrtcolearn import pipeline

        rows = pipeline.inspect_run(run_dir)
        width = max([len(r["file"]) for r in rows], default=4)
        for r in rows:
            typer.echo(f"{r['file']:<{width}}  {r['kind']:<7}  {r['bytes']:>11}  {r['sha256']}")
    guard(body)
