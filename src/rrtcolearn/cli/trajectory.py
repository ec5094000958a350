"""The commands that use a plan file's trajectory: export (samples and tracking gains),
track (open-loop and tracked rollouts) and animate."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rrtcolearn.cli.common import SeedOpt, SystemOpt, guard, out_console, print_summary
from rrtcolearn.errors import ArtefactError, ConfigError


def _checked_plan(plan_file: Path, system_name: str | None):
    """(plan file content, its system), the file checked to be what it claims."""
    from rrtcolearn import pipeline
    from rrtcolearn.evaluate import PlanCheckError, check_plan

    d = pipeline.read_plan(plan_file)
    system = pipeline.plan_system(d, system_name)
    try:  # the file is what it claims before anything is made from it
        check_plan(system, d)
    except PlanCheckError as exc:
        raise ArtefactError(f"{plan_file}: {exc}") from None
    return d, system


def _write_table(target: Path, fmt: str, header: list[str], columns: list[str],
                 arrays: dict, table) -> None:
    """A CSV (``header`` lines as # comments, then the column names; whole numbers in an
    ``edge`` column) or an npz of ``arrays`` with ``columns``."""
    import numpy as np

    from rrtcolearn.data.store import atomic_write_bytes, atomic_write_text

    if fmt == "csv":
        whole = [c == "edge" for c in columns]
        lines = [f"# {h}" for h in header] + [",".join(columns)] + [
            ",".join(str(int(v)) if w else repr(float(v)) for v, w in zip(row, whole,
                                                                          strict=True))
            for row in table]
        atomic_write_text(target, "\n".join(lines) + "\n")
    else:
        import io

        buffer = io.BytesIO()
        np.savez(buffer, columns=np.array(columns), header=np.array(header), **arrays)
        atomic_write_bytes(target, buffer.getvalue())


def export(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    dt: Annotated[float | None, typer.Option(
        help="sample step (s), a whole multiple of the plan's integration step, or a whole "
             "fraction of it (every edge re-simulated at that finer step, for an open-loop "
             "replay; docs/formats.md) (default: that step)")] = None,
    fmt: Annotated[str, typer.Option("--format", help="csv or npz")] = "csv",
    out: Annotated[Path | None, typer.Option(
        "--out", help="output file (default: the plan file with .csv or .npz)")] = None,
    gains: Annotated[bool, typer.Option(
        "--gains", help="also write the tracking controller: the nominal at the plan's step "
        "and its time-varying LQR gains K(t), to OUT's name with -gains")] = False,
    system_name: SystemOpt = None,
) -> None:
    """Time, state, input and costate samples along a plan's path, re-simulated from its
    edges (the trajectory to execute); with --gains the tracking controller's gains."""
    def body():
        import numpy as np

        from rrtcolearn.evaluate import sample_path

        if fmt not in ("csv", "npz"):
            raise ConfigError(f"--format {fmt!r}: give csv or npz")
        if dt is not None and not dt > 0:
            raise ConfigError(f"--dt {dt}: give a positive step")
        d, system = _checked_plan(plan_file, system_name)
        try:
            samples = sample_path(system, d, dt)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        target = out if out is not None else plan_file.with_suffix(f".{fmt}")
        columns = ["t", *system.state_names, *system.input_names,
                   *(f"lambda_{name}" for name in system.state_names), "edge"]
        header = [
            f"rrtcolearn trajectory: system {system.name}, {system.n_states} states, "
            f"{system.n_inputs} inputs, integration step {d['dt']} s"
            + (f", re-simulated at {dt} s" if dt is not None and dt < d["dt"] else ""),
            "units: t in seconds; states, inputs and costates (lambda_, nan on "
            "random-control edges) in the units of the system's definition",
            "inputs between rows: continuous within an extremal edge (interpolate linearly), "
            "held within a random-control edge; where edges meet, two rows with the same t: "
            "the end of the one edge, then the start of the next (the input jumps there)"]
        table = np.column_stack([samples["t"], samples["state"], samples["input"],
                                 samples["costate"], samples["edge"]])
        _write_table(target, fmt, header, columns, samples, table)
        figures = {"samples": len(samples["t"]),
                   "duration_s": round(float(samples["t"][-1]), 4),
                   "edges": int(samples["edge"][-1]) + 1, "columns": ", ".join(columns)}
        if gains:
            from rrtcolearn.tracking import TrackingController

            c = TrackingController.build(system, d)
            nom = c.nominal
            gain_names = [f"K_{u}_{x}" for u in system.input_names for x in system.state_names]
            K = np.concatenate([c.K, c.K[-1:]]).reshape(len(nom.t), -1)
            g_target = target.with_name(f"{target.stem}-gains{target.suffix}")
            _write_table(g_target, fmt, [
                f"rrtcolearn tracking gains: system {system.name}, step {nom.dt} s, state "
                f"weight {c.state_weight:g} x Bryson's Q, input weight by the {c.input_rule} "
                f"rule (the self-test's), terminal cost "
                f"{c.terminal}",
                "u = clip(u_nom - K (x - x_nom), input box) with K held from each row's t to "
                "the next (the last row's K: the last step's); angles of x - x_nom the short "
                "way round",
                "K_<input>_<state>: the gain of that input on that state's error; "
                f"input box low {c.u_low.tolist()} high {c.u_high.tolist()}"],
                ["t", *system.state_names, *system.input_names, *gain_names],
                {"t": nom.t, "state": nom.state, "input": nom.input,
                 "K": np.concatenate([c.K, c.K[-1:]]), "u_low": c.u_low, "u_high": c.u_high},
                np.column_stack([nom.t, nom.state, nom.input, K]))
            figures["gains"] = str(g_target)
        print_summary(f"export -> {target}", figures)
    guard(body)


def track(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    rollouts: Annotated[int, typer.Option(help="runs, open-loop and tracked each")] = 100,
    true_system: Annotated[str | None, typer.Option(
        "--true-system", help="the system the runs happen on (module:attribute or a "
        "registered name; the same states and inputs as the plan's, other parameters); "
        "default the plan's own model")] = None,
    noise: Annotated[float, typer.Option(
        help="process noise: standard deviation per sqrt(s), a fraction of each state's "
             "box width")] = 0.0,
    start_error: Annotated[float, typer.Option(
        "--start-error", help="start state off by a uniform draw within +- this fraction of "
        "each state's box width")] = 0.0,
    state_weight: Annotated[float, typer.Option(
        "--state-weight", help="multiplies the state weight Q the self-test picks (a multiple "
        "of Bryson's rule from the boxes, as the goal LQR)")] = 1.0,
    seed: SeedOpt = None,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="write the figure of the nominal and the runs' spread (PNG)")] = None,
    system_name: SystemOpt = None,
) -> None:
    """Run a plan open-loop and tracked by time-varying LQR, on the model or another
    system, with noise and a start error; goal reached, errors, inputs at the limit,
    obstacle entries."""
    def body():
        from rrtcolearn import tracking

        if rollouts < 1:
            raise ConfigError(f"--rollouts {rollouts}: give at least 1")
        if not (noise >= 0 and start_error >= 0):
            raise ConfigError("--noise and --start-error must not be negative")
        if not state_weight > 0:
            raise ConfigError(f"--state-weight {state_weight}: give a positive factor")
        d, system = _checked_plan(plan_file, system_name)
        truth = None
        if true_system is not None:
            from rrtcolearn.systems import make

            try:
                truth = make(true_system)
            except ValueError as exc:
                raise ConfigError(f"--true-system: {exc}") from None
            tracking.check_truth(system, truth)
        c = tracking.TrackingController.build(system, d, state_weight=state_weight)
        runs = tracking.rollouts(c, rollouts, truth=truth, noise=noise,
                                 start_error=start_error, seed=0 if seed is None else seed)
        rows = [tracking.summarise(c, r) for r in runs]
        from rich.table import Table

        table = Table(title=f"track {plan_file}: {rollouts} runs on "
                      f"{true_system or 'the model'}, noise {noise:g}, start error "
                      f"{start_error:g}, state weight {c.state_weight:g} x Bryson's, input "
                      f"weight the {c.input_rule} rule, seed "
                      f"{0 if seed is None else seed}")
        table.add_column("")
        for name in ("open-loop", "tracked"):
            table.add_column(name, justify="right")
        tol = c.problem.goal_tolerance
        for key, label in (("reached", f"share of runs reaching the goal (<= {tol:g})"),
                           ("reached_2x", f"share within 2x ({2 * tol:g})"),
                           ("final_error_median", "final error, median"),
                           ("final_error_max", "final error, largest"),
                           ("deviation_median", "largest deviation, median"),
                           ("deviation_max", "largest deviation, largest"),
                           ("time_at_limit", "share of the time at the input limit"),
                           ("inputs_in_box", "inputs within the box"),
                           ("obstacle_entries", f"runs entering an obstacle (of {rollouts})"),
                           ("constraint_exits",
                            f"runs leaving the state constraints (of {rollouts})")):
            table.add_row(label, *(_figure(r[key]) for r in rows))
        out_console.print(table)
        if plot is not None:
            from rrtcolearn.animation import tracking_figure
            from rrtcolearn.plotting import save_figure

            fig = tracking_figure(system, c.nominal.t, c.nominal.state,
                                  {"open-loop": runs[0].states, "tracked": runs[1].states},
                                  title=f"{plan_file.name}: {rollouts} runs")
            save_figure(fig, plot)
            typer.echo(f"figure -> {plot}")
    guard(body)


def _figure(v) -> str:
    if isinstance(v, bool) or isinstance(v, int):
        return str(v)
    return f"{v:.3g}" if abs(v) >= 1 or v == 0 or v != v else f"{v:.3f}"


def animate(
    plan_file: Annotated[Path, typer.Argument(help="plan file (JSON) written by plan or run")],
    out: Annotated[Path, typer.Option("--out", help="animation file: .gif (pillow) or .mp4 "
                                      "(needs ffmpeg)")],
    fps: Annotated[float, typer.Option(help="frames per second (real time up to 120 "
                                       "frames)")] = 20.0,
    system_name: SystemOpt = None,
) -> None:
    """Animate a plan's motion: the bodies where the system declares them (pendulum,
    cart-pole, acrobot, quadrotor), else its states against time."""
    def body():
        from rrtcolearn.animation import animate as write
        from rrtcolearn.evaluate import sample_path

        if not fps > 0:
            raise ConfigError(f"--fps {fps}: give a positive rate")
        d, system = _checked_plan(plan_file, system_name)
        s = sample_path(system, d)
        frames = write(system, s["t"], s["state"], out, fps=fps,
                       title=f"{system.name}: {plan_file.name}")
        print_summary(f"animate -> {out}", {"frames": frames,
                                            "duration_s": round(float(s["t"][-1]), 3),
                                            "bytes": out.stat().st_size})
    guard(body)
