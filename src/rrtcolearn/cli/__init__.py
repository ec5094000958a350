"""Command-line interface: parse, validate, call the library, print.

Only typer, rich and the standard library are imported at start-up: the library (numpy,
numba, scipy, pydantic, sympy, matplotlib) is imported by the command that needs it, so
``--help`` and a single ``plan`` pay only for what they use.

This module holds the typer ``app`` and the console entry point ``main``; `common` what the
commands share; `running` generate, clean, fit, run and experiment; `planning` plan;
`trajectory` export, track and animate; `inspection` systems and inspect.
"""

from __future__ import annotations

import gc
import signal
import sys
from typing import Annotated

import typer
from typer.core import TyperGroup

try:  # recent typer versions vendor click; older ones use it directly
    from typer._click import exceptions as _click_errors
except ImportError:  # pragma: no cover
    from click import exceptions as _click_errors

from rrtcolearn.cli import inspection, planning, running, trajectory
from rrtcolearn.cli.common import INTERRUPTED, Interrupted, console, out_console, printable, state


class _OneLineErrors(TyperGroup):
    """Usage errors (a malformed option value, an unknown option) as one line, exit 2."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except _click_errors.NoArgsIsHelpError as exc:
            print(exc.ctx.get_help() if exc.ctx else str(exc))
            sys.exit(0)
        except _click_errors.ClickException as exc:
            console.print(f"[bold red]error:[/] {printable(exc.format_message())}",
                          highlight=False, soft_wrap=True)
            sys.exit(exc.exit_code)
        except typer.Abort:
            console.print(INTERRUPTED)
            sys.exit(130)
        sys.exit(rv if isinstance(rv, int) else 0)


app = typer.Typer(
    cls=_OneLineErrors,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="RRT-CoLearn: kinodynamic planning with learned cost-to-go and learned steering.",
)


def _print_version(value: bool) -> None:
    if value:
        from rrtcolearn import __version__

        out_console.print(f"rrtcolearn {__version__}")
        raise typer.Exit(0)


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="show tracebacks on errors")] = False,
    version: Annotated[bool, typer.Option("--version", help="print the version",
                                          is_eager=True, callback=_print_version)] = False,
) -> None:
    state["debug"] = debug


# in the order --help lists them
for command in (inspection.systems, running.generate, running.clean, running.fit,
                planning.plan, running.run, running.experiment, trajectory.export,
                trajectory.track, trajectory.animate, inspection.inspect):
    app.command()(command)


def _interrupt(signum, frame) -> None:
    raise Interrupted


def main() -> None:
    """Console entry point."""
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        app()
    except (Interrupted, KeyboardInterrupt):
        console.print(INTERRUPTED)
        sys.exit(130)
    finally:
        # the process ends here: the interpreter's shutdown would garbage-collect every object
        # that numba, scipy and the model created (0.2-0.3 s after a plan); frozen, they are
        # left to the operating system. atexit handlers (worker pools) still run.
        gc.freeze()
