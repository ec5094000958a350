"""Anytime planning on the pendulum swing-up: two anytime schemes at equal CPU against the
first solution and against the collocation optimum.

Problems: start (-pi, 0), goal (0, 0), tolerance 0.1, w = 1, unbounded and u_max = 2 (by
truncation, on one unbounded model built as `make bench` builds it). Each seeded query runs
`rrtcolearn.anytime.solve_with_restarts` for ``--budget`` CPU seconds (process CPU) with each
scheme: plain restarts (the baseline), and restarts whose every path is shortcut to the goal
(`planning.improve.shortcut`, what ``plan.anytime`` runs). The first solution is the plain
planner's (same seed) in both. The reference optimum is the collocation
(`baselines.collocation.problem_optimum`, CasADi + IPOPT, 60 intervals) to the planner's own
goal ball, free final time up to 15 s, from the straight-line guess at several initial
durations and from the cheapest path the schemes found: the cheapest converged solution.
The optimum to the goal point (the same collocation, state bounds lifted) is printed beside
it.

Beside it, OMPL's RRT's first solution on the same problem (where OMPL is installed and the
problem has an input box: u_max = 2), its path priced with w + u^2/2 by re-simulation
(`evaluate.replay`), 10 s per query. The best cost against planning CPU (median and
quartiles over the queries, the optimum as a line) is drawn into ``--figure``.

    python bench/anytime.py [--queries 20] [--budget 1.0] [--figure runs/anytime.png]

Prints one line per problem and, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import statistics
from functools import partial
from pathlib import Path

import numpy as np

from rrtcolearn import pipeline
from rrtcolearn.anytime import solve_with_restarts
from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.planning.improve import shortcut
from rrtcolearn.planning.rrt import RRTCoLearn
from rrtcolearn.planning.termination import TerminationCondition
from rrtcolearn.systems import make

START, GOAL, TOLERANCE = np.array([-np.pi, 0.0]), np.array([0.0, 0.0]), 0.1
INITIAL_DURATIONS = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0)
# the anytime schemes side by side at equal CPU: the restart baseline, and restarts whose
# every path is shortcut to the goal (`planning.improve.shortcut`, what plan.anytime runs)
SCHEMES = {"restarts": None, "restarts+shortcuts": shortcut}


def point_optimum(system, u_max: float | None, w: float = 1.0) -> float | None:
    """The collocation optimum to the goal point (`baselines.collocation.optimal_cost`, state
    bounds lifted), the cheapest over straight-line guesses of INITIAL_DURATIONS (None without
    CasADi or a converged solve)."""
    from rrtcolearn.baselines.collocation import optimal_cost
    from rrtcolearn.baselines.direct import casadi_available

    if not casadi_available():
        return None
    free = [np.inf] * len(START)
    r = optimal_cost(system, START, GOAL, time_weight=w, u_max=u_max, n_intervals=60,
                     durations=INITIAL_DURATIONS, t_max=15.0, state_low=[-v for v in free],
                     state_high=free)
    return float(r.cost) if r.success else None


def ball_optimum(problem, plan, w: float = 1.0) -> tuple[float | None, str | None]:
    """The collocation optimum to the planner's own goal region (the ball of TOLERANCE,
    `baselines.collocation.problem_optimum`), from straight-line guesses and from the
    planner's best path (re-simulated); (cost, the guess that won), or (None, None) without
    CasADi or a converged solve."""
    from rrtcolearn.baselines.collocation import problem_optimum
    from rrtcolearn.baselines.direct import casadi_available
    from rrtcolearn.evaluate import sample_path

    if not casadi_available():
        return None, None
    sp = sample_path(problem.system, plan)
    r = problem_optimum(problem, time_weight=w, n_intervals=60, durations=INITIAL_DURATIONS,
                        t_max=15.0, path=(sp["t"], sp["state"], sp["input"][:-1]))
    return (float(r.cost), r.guess) if r.success else (None, None)


def ompl_first_costs(problem, queries: int) -> list[float] | None:
    """OMPL RRT's first-solution costs (re-simulated) on ``problem``, seeds 0..queries-1;
    None without OMPL or without an input box."""
    from rrtcolearn import planners
    from rrtcolearn.evaluate import replay

    peer = planners.make("ompl-RRT", time_weight=1.0)
    if peer.supports(problem) is not None:
        return None
    costs = []
    for seed in range(queries):
        p = peer.solve(problem, TerminationCondition(10.0), seed)
        if p.solved:
            costs.append(replay(problem, p)["path_cost"])
    return costs


def best_cost_curves(progress: list[list[list[float]]], grid: np.ndarray) -> np.ndarray:
    """(queries, len(grid)) best cost at each CPU time of ``grid`` (NaN before a query's
    first solution), from each query's [CPU, best cost] improvements."""
    out = np.full((len(progress), len(grid)), np.nan)
    for q, steps in enumerate(progress):
        for t, c in steps:
            out[q, grid >= t] = c
    return out


def draw(curves: dict, grid: np.ndarray, optima: dict, path: str) -> None:
    """Median and quartiles of the best cost against CPU per problem and scheme, each
    problem's optimum dashed; CPU on a log scale (the shortcuts converge within 0.1 s)."""
    from rrtcolearn.plotting import plt, save_figure

    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    drawn = set()
    for name, c in curves.items():
        # a query without a solution yet counts as infinitely dear: the median is drawn from
        # when half the queries have their first solution, each quartile from when it is finite
        c = np.where(np.isnan(c), np.inf, c)
        with np.errstate(invalid="ignore"):  # inf - inf between two unsolved queries
            q1, med, q3 = np.percentile(c, [25, 50, 75], axis=0)
        (line,) = ax.plot(np.where(np.isfinite(med), grid, np.nan), med,
                          ls="--" if "shortcuts" in name else "-", label=f"{name}: median")
        shown = np.isfinite(q3)
        ax.fill_between(grid[shown], q1[shown], q3[shown], alpha=0.2, color=line.get_color())
        opt = optima.get(name)
        if opt is not None and round(opt, 6) not in drawn:
            drawn.add(round(opt, 6))
            ax.axhline(opt, color="k", ls=":", lw=1, label="collocation optimum (goal ball)")
    ax.set_xscale("log")
    ax.set_xlabel("planning CPU (s)")
    ax.set_ylabel("best path cost (w T + integral of u^2/2)")
    ax.set_title("Anytime schemes at equal CPU, pendulum swing-up, tolerance 0.1\n"
                 "(quartiles shaded; a query not yet solved counts as infinitely dear)")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=20)
    ap.add_argument("--budget", type=float, default=1.0, help="CPU seconds per query")
    ap.add_argument("--figure", default="runs/anytime.png", help="best cost against CPU")
    args = ap.parse_args(argv)
    grid = np.geomspace(0.005, args.budget, 241)
    curves, optima = {}, {}
    system = make("pendulum")
    cfg = pipeline.resolve(Config(), system)
    g = cfg.generate
    data, _ = generate_data(system, 1, g.n_simulations, max_cost=cfg.max_cost)
    cleaned, _ = clean_data(data, d=cfg.clean.d, k_max=cfg.clean.k_max, seed=1)
    model = pipeline.FittedModel(system, cfg, pipeline.fit_functions(system, cleaned, cfg),
                                 float(cleaned.duration.max()), g.max_state_distance)
    out = {}
    for name, u_max in (("unbounded", None), ("u_max 2", 2.0)):
        problem = pipeline.make_problem(system, cfg, START, GOAL, TOLERANCE, u_max=u_max)
        planner = RRTCoLearn(problem, model.functions, model.planner_settings())
        point = point_optimum(system, u_max)
        ompl = ompl_first_costs(problem, args.queries)
        cheapest = None  # the cheapest path any scheme found: a guess of the ball optimum
        # (first, best, first CPU, solves, progress) per scheme; the schemes alternate query
        # by query, so that both see the same load (the first-solution CPU ratio)
        runs = {scheme: ([], [], [], [], []) for scheme in SCHEMES}
        for seed in range(args.queries):
            for scheme, improve in SCHEMES.items():
                improve = None if improve is None else partial(improve, planner)
                p = solve_with_restarts(planner.solve,
                                        TerminationCondition(None, None, args.budget), seed,
                                        improve=improve)
                a = p.extra["anytime"]
                if not a["progress"]:
                    continue
                first, best, first_cpu, solves, progress = runs[scheme]
                first.append(a["first_solution_cost"])
                first_cpu.append(a["first_solution_cpu_s"])
                best.append(p.path_cost)
                if cheapest is None or p.path_cost < cheapest.path_cost:
                    cheapest = p
                solves.append(a["solves"])
                progress.append(a["progress"])
        optimum, won = ball_optimum(problem, cheapest) if cheapest else (None, None)
        for scheme, (first, best, first_cpu, solves, progress) in runs.items():
            key = f"{name}, {scheme}"
            curves[key] = best_cost_curves(progress, grid)
            optima[key] = optimum
            row = {"solved": f"{len(best)}/{args.queries}",
                   "first_cost_median": round(statistics.median(first), 4),
                   "best_cost_median": round(statistics.median(best), 4),
                   "best_over_first_median": round(statistics.median(
                       b / f for b, f in zip(best, first, strict=True)), 4),
                   "first_solution_cpu_s_median": round(statistics.median(first_cpu), 4),
                   "solves_median": statistics.median(solves),
                   "collocation_optimum": None if optimum is None else round(optimum, 4),
                   "optimum_from": won,
                   "point_goal_optimum": None if point is None else round(point, 4)}
            if optimum is not None:
                row["first_over_optimum"] = round(row["first_cost_median"] / optimum, 4)
                row["best_over_optimum"] = round(row["best_cost_median"] / optimum, 4)
            if ompl:
                row["ompl_rrt_solved"] = f"{len(ompl)}/{args.queries}"
                row["ompl_rrt_first_cost_median"] = round(statistics.median(ompl), 4)
                row["best_over_ompl_rrt_first"] = round(
                    row["best_cost_median"] / row["ompl_rrt_first_cost_median"], 4)
                row["first_over_ompl_rrt_first"] = round(
                    row["first_cost_median"] / row["ompl_rrt_first_cost_median"], 4)
            else:
                row["ompl_rrt"] = "not run: " + ("OMPL needs an input box" if ompl is None
                                                  else "no solution")
            out[key] = row
            print(f"{key}: " + " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
        # both schemes' first solve is the same plain solve: the same first paths
        out[f"{name}: same first solutions"] = len({tuple(r[0]) for r in runs.values()}) == 1
        base, ours = (out[f"{name}, {k}"] for k in SCHEMES)
        # the same seeds' first solutions under both schemes: their CPU ratio
        out[f"{name}: first-solution CPU, shortcuts / restarts"] = round(
            ours["first_solution_cpu_s_median"] / base["first_solution_cpu_s_median"], 4)
        for k in (f"{name}: same first solutions",
                  f"{name}: first-solution CPU, shortcuts / restarts"):
            print(f"{k}: {out[k]}", flush=True)
    Path(args.figure).parent.mkdir(parents=True, exist_ok=True)
    draw(curves, grid, optima, args.figure)
    print(f"figure: {args.figure}")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
