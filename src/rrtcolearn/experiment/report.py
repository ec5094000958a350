"""Result files, figures and ``report.md`` of an experiment."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import atomic_write_text, load_dataset, write_json
from rrtcolearn.evaluate import held_out_errors
from rrtcolearn.experiment.layout import (
    ROW_FIELDS,
    dataset_name,
    epoch_config,
    experiment_problems,
    planning_problem,
    problem_system,
    write_csv,
)
from rrtcolearn.experiment.ompl_format import LogExperiment, write_database, write_log
from rrtcolearn.planners import RRTCoLearnPlanner
from rrtcolearn.planning.termination import TerminationCondition

PAPER = {"plan_time_s_median": 2.36, "nodes_median": 84, "nodes_std": 180,
         "steer_mse_median": 0.11, "offline_s_per_epoch": 25 * 60}


def _limit(config: Config) -> TerminationCondition:
    """The runs' wall and CPU time limits."""
    e = config.experiment
    return TerminationCondition(e.time_limit, e.max_iterations, e.cpu_time_limit)


def _stats(rows: list[dict]) -> dict:
    solved = [r for r in rows if r.get("solved")]
    t = np.array([r["time"] for r in rows if r.get("time") is not None
                  and np.isfinite(r["time"])])

    def med(key, src=solved):
        v = [r[key] for r in src if r.get(key) is not None]
        return float(np.median(v)) if v else None

    return {
        "runs": len(rows),
        "success_rate": len(solved) / len(rows) if rows else None,
        "time_median": float(np.median(t)) if t.size else None,
        "time_p90": float(np.quantile(t, 0.9)) if t.size else None,
        "nodes_median": med("nodes", rows),
        "nodes_std": float(np.std([r["nodes"] for r in rows])) if rows else None,
        "path_cost_median": med("path_cost"),
        "path_duration_median": med("path_duration"),
        "max_abs_u": max((r["max_abs_u"] for r in solved), default=None),
    }


def d_grid_search(exp_dir: Path, config: Config) -> list[dict]:
    """Fig. 4's message on real data: clean epoch 0's data with each d, fit, and measure the
    held-out cost and steering errors (paper Section 4: the grid search that picked d)."""
    pr = experiment_problems(config)[0]
    cfg = epoch_config(config, pr, 0)
    run_dir = exp_dir / "epoch-00" / dataset_name(pr)
    raw, _ = load_dataset(run_dir / pipeline.DATASET_FILE)
    system = pipeline.system_from_config(cfg)
    held, _ = generate_data(system, cfg.seed + 1, config.experiment.held_out_simulations,
                            time_weight=pr.time_weight, u_max=pr.u_max)
    rows = []
    for d in config.experiment.d_grid:
        cleaned, _ = clean_data(raw, d=d, k_max=cfg.clean.k_max, seed=0)
        functions = pipeline.fit_functions(system, cleaned, cfg)
        err = held_out_errors(system, functions, held, n_queries=1000,
                              time_weight=pr.time_weight)
        # beyond the paper: the planner's own figures, cheap enough to measure here
        model = pipeline.FittedModel(system, cfg, functions, float(cleaned.duration.max()),
                                     cfg.generate.max_state_distance)
        problem = planning_problem(config, pr, system)
        plans = [RRTCoLearnPlanner(model).solve(
            problem, _limit(config), seed)
            for seed in range(config.experiment.d_grid_plans)]
        rows.append({"d": d, "kept_points": len(cleaned),
                     "cost_rel_error_median": float(np.median(err.cost_rel_error)),
                     "param_error_median": float(np.median(err.param_error)),
                     "steer_mse_median": float(np.median(err.steer_mse)),
                     "accepted_fraction": err.accepted_fraction,
                     "plan_success_rate": float(np.mean([p.solved for p in plans])),
                     "plan_cpu_s_median": float(np.median([p.planning_cpu_s for p in plans])),
                     "plan_nodes_median": float(np.median([p.nodes for p in plans]))})
    # the paper's criterion: the error in cost and in the costate parameters on new data;
    # the choice minimises their sum, each relative to its best value over the grid
    c = np.array([r["cost_rel_error_median"] for r in rows])
    s = np.array([r["param_error_median"] for r in rows])
    score = c / c.min() + s / s.min()
    for r, sc in zip(rows, score, strict=True):
        r["score"] = float(sc)
        r["chosen"] = bool(sc == score.min())
    return rows


def _figures(exp_dir: Path, config: Config, rows: list[dict], grid: list[dict]) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rrtcolearn.plotting import plot_tree, save_figure

    files = {}
    main = experiment_problems(config)[0]
    ours = [r for r in rows if r["planner"] == "rrtcolearn" and r["problem"] == main.name]
    if ours:
        # the tree of a typical run: epoch 0's run with the median number of nodes
        epoch0 = sorted((r for r in ours if r["epoch"] == 0), key=lambda r: r["nodes"])
        typical = epoch0[len(epoch0) // 2]
        model = pipeline.load_model(exp_dir / "epoch-00" / dataset_name(main))
        plan = RRTCoLearnPlanner(model).solve(
            planning_problem(config, main, model.system),
            _limit(config), typical["seed"])
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        plot_tree(ax, plan)
        save_figure(fig, exp_dir / "tree.png")
        files["tree"] = "tree.png"
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        epochs = sorted({r["epoch"] for r in ours})
        ax.boxplot([[r["time"] * 1e3 for r in ours if r["epoch"] == e] for e in epochs],
                   tick_labels=[str(e) for e in epochs])
        ax.set_xlabel("epoch")
        ax.set_ylabel("planning CPU time [ms]")
        ax.set_yscale("log")
        ax.set_title(f"RRT-CoLearn planning time per epoch ({main.name})")
        save_figure(fig, exp_dir / "times_per_epoch.png")
        files["times"] = "times_per_epoch.png"
    if grid:
        fig, ax1 = plt.subplots(figsize=(6.4, 3.6))
        d = [r["d"] for r in grid]
        ax1.plot(d, [r["cost_rel_error_median"] for r in grid], "o-", color="tab:blue",
                 label="cost-to-go relative error")
        ax1.set_xscale("log")
        ax1.set_xlabel("cleaning radius d")
        ax1.set_ylabel("median relative error of J", color="tab:blue")
        ax2 = ax1.twinx()
        ax2.plot(d, [r["steer_mse_median"] for r in grid], "s--", color="tab:red",
                 label="steering MSE")
        ax2.set_ylabel("median steering MSE", color="tab:red")
        best = next(r for r in grid if r["chosen"])
        ax1.axvline(best["d"], color="0.5", lw=1)
        ax1.set_title(f"grid search over d: chosen d = {best['d']:g}")
        save_figure(fig, exp_dir / "d_grid.png")
        files["d_grid"] = "d_grid.png"
    return files


def _fmt(v, scale: float = 1.0, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v * scale:.{digits}g}"
    return str(v)


def write_outputs(exp_dir: Path, config: Config, rows: list[dict], offline: list[dict],
                  skipped: dict[str, str]) -> dict:
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S")
    write_csv(exp_dir / "runs.csv", rows, ROW_FIELDS)
    off_fields = ["epoch", "dataset", "method", "simulations", "raw_points", "kept_points",
                  "generate_cpu_s", "clean_cpu_s", "fit_cpu_s", "offline_cpu_s",
                  "cpu_s_per_solve"]
    write_csv(exp_dir / "offline.csv", offline, off_fields)
    experiments = []
    system = problem_system(config, experiment_problems(config)[0]).name
    label = "".join(c if c.isalnum() or c in "._-" else "-" for c in system)
    for pr in experiment_problems(config):
        planners: dict[str, list[dict]] = {}
        for r in rows:
            if r["problem"] == pr.name:
                planners.setdefault(r["planner"], []).append(r)
        problem = planning_problem(config, pr)
        setup = (f"{system} from {problem.start.tolist()} to {problem.goal.tolist()}, goal "
                 f"tolerance {pr.goal_tolerance}, u_max {pr.u_max}, time weight "
                 f"{pr.time_weight}")
        experiments.append(LogExperiment(
            name=f"{label}-{pr.name}", time_limit=config.experiment.time_limit,
            total_time=float(sum(r.get("wall_s") or 0.0 for rs in planners.values()
                                 for r in rs)),
            seed=config.seed, setup=setup, planners=planners,
            properties={"u_max": ("REAL", "nan" if pr.u_max is None else str(pr.u_max)),
                        "goal_tolerance": ("REAL", str(pr.goal_tolerance)),
                        "time_weight": ("REAL", str(pr.time_weight))}))
    for exp in experiments:
        write_log(exp_dir / "ompl" / f"{exp.name}.log", [exp], date)
    write_database(exp_dir / "benchmark.db", experiments, date)
    grid = d_grid_search(exp_dir, config) if config.experiment.d_grid else []
    write_csv(exp_dir / "d_grid.csv", grid, ["d", "kept_points", "cost_rel_error_median",
                                             "param_error_median", "steer_mse_median",
                                             "accepted_fraction", "plan_success_rate",
                                             "plan_cpu_s_median", "plan_nodes_median", "score",
                                             "chosen"])
    figures = _figures(exp_dir, config, rows, grid)
    summary = _summary(config, rows, offline, grid, skipped)
    write_json(exp_dir / "summary.json", summary)
    atomic_write_text(exp_dir / "report.md", _report(config, summary, figures))
    return summary


def _summary(config: Config, rows, offline, grid, skipped) -> dict:
    table = {}
    problems = experiment_problems(config)
    for pr in problems:
        for planner in config.experiment.planners:
            sel = [r for r in rows if r["problem"] == pr.name and r["planner"] == planner]
            if sel:
                table.setdefault(pr.name, {})[planner] = _stats(sel)
    indirect = [o for o in offline if o["method"] == "indirect"]
    main = problems[0].name
    per_epoch = {}
    for o in indirect:
        if o["dataset"] == dataset_name(problems[0]):
            per_epoch[o["epoch"]] = o["offline_cpu_s"]
    return {
        "epochs": config.experiment.epochs,
        "runs_per_epoch": config.experiment.runs_per_epoch,
        "main_problem": main,
        "offline_cpu_s_per_epoch_median": float(np.median(list(per_epoch.values())))
        if per_epoch else None,
        "offline": offline,
        "planners": table,
        "d_grid": grid,
        "skipped_planners": skipped,
        "system": problem_system(config, problems[0]).name,
    }


def _report(config: Config, summary: dict, figures: dict) -> str:
    main = summary["main_problem"]
    ours = summary["planners"].get(main, {}).get("rrtcolearn", {})
    lines = ["# RRT-CoLearn experiment report", "",
             f"System {summary['system']}: {summary['epochs']} epochs x "
             f"{summary['runs_per_epoch']} runs per epoch; "
             "each epoch has its own freshly generated and cleaned datasets. Times are CPU "
             "seconds of the planning process (process or thread CPU time), not wall time. "
             "Every plan is re-simulated from its recorded controls or costates and checked "
             "against the problem (rrtcolearn.evaluate.replay); only such plans count as "
             "solved.", ""]
    grid = summary["d_grid"]
    chosen = next((g for g in grid if g["chosen"]), None)
    first = experiment_problems(config)[0]
    if summary["system"] == "pendulum" and first.u_max is None:
        lines += _against_paper(config, summary, ours, grid)
    elif summary["system"] == "pendulum":
        lines += [f"(The paper's figures are for the unbounded pendulum; the first problem, "
                  f"{first.name}, sets u_max = {first.u_max:g}: put an unbounded problem "
                  "first to see them beside it.)", ""]
    for pr in experiment_problems(config):
        planners = summary["planners"].get(pr.name, {})
        if not planners:
            continue
        lines += [f"## {pr.name}: {_limit_label(config, pr)}, w = {pr.time_weight:g}, "
                  f"tolerance {pr.goal_tolerance:g}", "",
                  "| planner | runs | success | CPU median | CPU p90 | nodes | path cost | "
                  "duration | max abs u | time vs RRT-CoLearn | RRT-CoLearn's CPU / this | "
                  "cost vs RRT-CoLearn | nodes vs RRT-CoLearn |",
                  "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
                  "| ---: | ---: |"]
        base = planners.get("rrtcolearn", {})
        for name, st in planners.items():
            def rel(key, st=st, base=base, inverse=False):
                a, b = st.get(key), base.get(key)
                if inverse:
                    a, b = b, a
                return f"{a / b:.3g}x" if a and b else "-"
            lines.append(
                f"| {name} | {st['runs']} | {_fmt(st['success_rate'])} | "
                f"{_fmt(st['time_median'], 1e3)} ms | {_fmt(st['time_p90'], 1e3)} ms | "
                f"{_fmt(st['nodes_median'])} | {_fmt(st['path_cost_median'])} | "
                f"{_fmt(st['path_duration_median'])} s | {_fmt(st['max_abs_u'])} | "
                f"{rel('time_median')} | {rel('time_median', inverse=True)} | "
                f"{rel('path_cost_median')} | {rel('nodes_median')} |")
        lines += ["", "CPU and nodes over all runs (an unsolved run at its full time); path "
                  "cost, duration and max abs u over the solved runs.", ""]
    if summary["skipped_planners"]:
        lines += ["Planners not run here: " + "; ".join(
            f"{k} ({v})" for k, v in summary["skipped_planners"].items()), ""]
    direct = [o for o in summary["offline"] if o["method"] == "direct"]
    indirect = [o for o in summary["offline"] if o["method"] == "indirect"]
    if direct and indirect:
        d_solve = np.median([o["cpu_s_per_solve"] for o in direct if o.get("cpu_s_per_solve")])
        d_pt = np.median([o["offline_cpu_s"] / max(o["kept_points"], 1) for o in direct])
        i_sim = np.median([o["generate_cpu_s"] / o["simulations"] for o in indirect])
        i_pt = np.median([o["offline_cpu_s"] / max(o["raw_points"], 1) for o in indirect])
        lines += ["## Offline cost: direct collocation against indirect rollouts", "",
                  "| | per trajectory | per data point |", "| --- | ---: | ---: |",
                  f"| direct (CasADi + IPOPT) | {d_solve * 1e3:.3g} ms | {d_pt * 1e3:.3g} ms |",
                  f"| indirect (this package) | {i_sim * 1e6:.3g} us | {i_pt * 1e6:.3g} us |",
                  f"| ratio | {d_solve / i_sim:.3g}x | {d_pt / i_pt:.3g}x |", ""]
    if grid:
        lines += ["## The cleaning radius d (paper Section 4, Fig. 4)", "",
                  "Epoch 0's raw data cleaned with each d, learners fitted, and errors measured "
                  "on 1000 held-out queries from newly generated data:", "",
                  "| d | kept points | J relative error | costate parameter error | "
                  "steering MSE | held-out accepted | plan success | plan CPU median | "
                  "plan nodes |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for g in grid:
            mark = " (chosen)" if g["chosen"] else ""
            lines.append(f"| {g['d']:g}{mark} | {g['kept_points']} | "
                         f"{g['cost_rel_error_median']:.3g} | {g['param_error_median']:.3g} | "
                         f"{g['steer_mse_median']:.3g} | {g['accepted_fraction']:.3g} | "
                         f"{g['plan_success_rate']:.2f} | "
                         f"{1e3 * g['plan_cpu_s_median']:.3g} ms | "
                         f"{g['plan_nodes_median']:g} |")
        lines += ["", "Chosen as the paper did, by the held-out error in cost and costate "
                  "parameters (the smallest sum of both, each relative to its best over the "
                  f"grid): d = {chosen['d']:g}; the paper chose 0.05. The planning columns "
                  f"({config.experiment.d_grid_plans} seeded swing-ups per d) are the "
                  "evaluation the paper calls proper but too costly.", ""]
    for key, title in (("tree", "The tree of a typical run (paper Fig. 2)"),
                       ("times", "Planning time per epoch (paper Fig. 3)"),
                       ("d_grid", "Grid search over d (paper Fig. 4)")):
        if key in figures:
            lines += [f"## {title}", "", f"![{title}]({figures[key]})", ""]
    lines += ["Files: runs.csv (one row per run), offline.csv, d_grid.csv, ompl/*.log (OMPL "
              "benchmark logs), benchmark.db (OMPL's SQLite schema; Planner Arena opens it), "
              "summary.json.", ""]
    return "\n".join(lines)


def _limit_label(config: Config, pr) -> str:
    """A problem's input limit as its plans have it: its u_max, else the system's own box."""
    if pr.u_max is not None:
        return f"u_max = {pr.u_max:g}"
    system = problem_system(config, pr)
    if not system.input_limited:
        return "unbounded inputs"
    low, high = system.input_limits()
    return "inputs in the system's box " + ", ".join(
        f"[{lo:g}, {hi:g}]" for lo, hi in zip(low.tolist(), high.tolist(), strict=True))


def _against_paper(config: Config, summary: dict, ours: dict, grid: list[dict]) -> list[str]:
    """The paper's pendulum figures beside ours."""
    lines = ["## Against the paper (pendulum swing-up, unbounded torque, tolerance "
             f"{experiment_problems(config)[0].goal_tolerance})", "",
             "| figure | paper | measured | ratio paper / measured |",
             "| --- | ---: | ---: | ---: |"]

    def ratio(paper, ours_v):
        return f"{paper / ours_v:.3g}x" if ours_v else "-"

    t = ours.get("time_median")
    lines.append(f"| median planning time | 2.36 s | {_fmt(t, 1e3)} ms | "
                 f"{ratio(PAPER['plan_time_s_median'], t)} |")
    lines.append(f"| median nodes | 84 | {_fmt(ours.get('nodes_median'))} | "
                 f"{ratio(84, ours.get('nodes_median'))} |")
    lines.append(f"| std of nodes | 180 | {_fmt(ours.get('nodes_std'))} | "
                 f"{ratio(180, ours.get('nodes_std'))} |")
    at_paper_d = next((g for g in grid if abs(g["d"] - config.clean.d) < 1e-12), None)
    mse = at_paper_d["steer_mse_median"] if at_paper_d else None
    lines.append(f"| median steering MSE (d = {config.clean.d:g}) | 0.11 | {_fmt(mse)} | "
                 f"{ratio(0.11, mse)} |")
    off = summary["offline_cpu_s_per_epoch_median"]
    lines.append(f"| offline time per epoch | about 25 min | {_fmt(off)} s | "
                 f"{ratio(PAPER['offline_s_per_epoch'], off)} |")
    lines += ["", f"Success rate: {_fmt(ours.get('success_rate'))}. The paper's hardware was a "
              "2012 laptop CPU; ratios mix algorithmic and hardware differences.", ""]
    return lines
