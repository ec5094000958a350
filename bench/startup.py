"""Start-up of the command line: what one `rrtcolearn plan` costs in a fresh process.

Prints, as medians over fresh processes (``--repeats``, default 5):

- wall and CPU time (user + system, of the child process) and peak resident memory of
  ``rrtcolearn --help``;
- the same of ``rrtcolearn plan`` for the pendulum's swing-up query
  (``--start=-3.14159,0 --goal 0,0 --goal-tolerance 0.1 --seed 1``);
- the planning CPU of the first query of a fresh process after `pipeline.load_model`, of
  the same query planned again in that process (warm), and their ratio;

then one JSON object with the same figures as its last line. The commands run as
``python -m rrtcolearn.cli`` with this interpreter and the current ``PYTHONPATH``, so
``PYTHONPATH=<checkout>/src python bench/startup.py`` measures another checkout. The model is
``--model RUN_DIR`` (default ``runs/pendulum-swingup``), made with ``rrtcolearn run --out
RUN_DIR`` first if it holds none.

With ``--systems RUN_DIR ...`` (fitted runs of any system, e.g. ``rrtcolearn run --system
acrobot --out RUN_DIR``) it also prints, per run, the medians of one ``rrtcolearn plan
--model RUN_DIR --seed 1 --max-iterations N`` (``--iterations``, default 300: about a second
of planning, so that the figure is the call's start-up plus a fixed amount of planning) of
the run's own query: wall, CPU, peak resident memory (the child's ``ru_maxrss``), the
planning CPU the plan file records and the rest (CPU minus planning: start-up and writing),
the size of the run's ``functions.npz``, and whether the call met <= 2 s wall and <= 500 MB.
MB are decimal (10^6 bytes; the kernel's ``ru_maxrss`` is in KiB): the stricter reading of
issue 31's target. Figures, not assertions: the machine may be shared.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

QUERY = ["--start=-3.14159,0", "--goal", "0,0", "--goal-tolerance", "0.1", "--seed", "1"]

# one fresh process: load the model, plan the query, then plan it again (warm)
FIRST_AND_WARM = """
import json, sys
from rrtcolearn import pipeline
model = pipeline.load_model(sys.argv[1])
cpu = [pipeline.plan(model, [-3.14159, 0.0], [0.0, 0.0], 0.1, 1).planning_cpu_s
       for _ in range(int(sys.argv[2]) + 1)]
print(json.dumps({"first": cpu[0], "warm": cpu[1:]}))
"""


# the targets of issue 31 for one plan call of a 4-state model
WALL_TARGET_S, RSS_TARGET_MB = 2.0, 500.0


def timed_process(args: list[str]) -> tuple[float, float, str, float]:
    """(wall s, CPU s of the child, its stdout, its peak resident memory in decimal MB) of
    one fresh process (`os.wait4`: that child's own resource usage, not all children's)."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(args, stdout=out, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        if proc.returncode != 0:
            sys.exit(f"failed ({proc.returncode}): {' '.join(args)}\n"
                     f"{err.read().decode(errors='replace')}")
        stdout = out.read().decode(errors="replace")
    return wall, usage.ru_utime + usage.ru_stime, stdout, usage.ru_maxrss * 1024 / 1e6


def medians(args: list[str], repeats: int) -> dict:
    runs = [timed_process(args) for _ in range(repeats)]
    walls, cpus, _, rss = zip(*runs, strict=True)
    return {"wall_s": round(statistics.median(walls), 3),
            "cpu_s": round(statistics.median(cpus), 3),
            "peak_rss_mb": round(statistics.median(rss), 1),
            "wall_s_all": [round(w, 3) for w in walls]}


def system_plan(cli: list[str], run: Path, iterations: int, repeats: int) -> dict:
    """Medians of one `rrtcolearn plan` of the run's own query (seed 1, ``iterations``)
    in fresh processes, after one untimed call; see the module docstring."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "plan.json")
        args = [*cli, "plan", "--model", str(run), "--seed", "1", "--max-iterations",
                str(iterations), "--out", out]
        timed_process(args)
        runs, planning = [], []
        for _ in range(repeats):
            runs.append(timed_process(args))
            with open(out, encoding="utf-8") as fh:
                planning.append(json.load(fh)["planning_cpu_s"])
    walls, cpus, _, rss = zip(*runs, strict=True)
    f = {"run": str(run), "wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus),
         "peak_rss_mb": statistics.median(rss), "planning_cpu_s": statistics.median(planning),
         "rest_cpu_s": statistics.median([c - p for c, p in zip(cpus, planning, strict=True)]),
         "functions_mb": (run / "functions.npz").stat().st_size / 1e6,
         "wall_s_all": walls}
    f = {k: (round(v, 3) if isinstance(v, float) else
             [round(w, 3) for w in v] if isinstance(v, tuple) else v) for k, v in f.items()}
    f["meets_targets"] = f["wall_s"] <= WALL_TARGET_S and f["peak_rss_mb"] <= RSS_TARGET_MB
    return f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=Path("runs/pendulum-swingup"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warm", type=int, default=5, help="warm plans per process")
    ap.add_argument("--systems", type=Path, nargs="*", default=[],
                    help="fitted runs whose own query one plan call plans (per run: wall, "
                    "CPU, peak RSS)")
    ap.add_argument("--iterations", type=int, default=300,
                    help="--max-iterations of the --systems plan calls")
    a = ap.parse_args()
    cli = [sys.executable, "-m", "rrtcolearn.cli"]
    for run in a.systems:
        if not (run / "model.json").is_file():
            sys.exit(f"no model in {run}: make one first, e.g. rrtcolearn run --system "
                     f"acrobot --out {run}")
    if not (a.model / "model.json").is_file():
        print(f"no model in {a.model}: rrtcolearn run --out {a.model}", flush=True)
        timed_process([*cli, "run", "--out", str(a.model)])
    # one untimed plan: the generated module, its numba cache and the build record exist
    with tempfile.TemporaryDirectory() as tmp:
        plan = [*cli, "plan", "--model", str(a.model), *QUERY, "--out",
                os.path.join(tmp, "plan.json")]
        timed_process(plan)
        figures = {"help": medians([*cli, "--help"], a.repeats),
                   "plan": medians(plan, a.repeats)}
    first, warm = [], []
    for _ in range(a.repeats):
        out = timed_process([sys.executable, "-c", FIRST_AND_WARM, str(a.model),
                             str(a.warm)])[2]
        d = json.loads(out.strip().splitlines()[-1])
        first.append(d["first"])
        warm.append(statistics.median(d["warm"]))
    figures["first_plan_cpu_s"] = round(statistics.median(first), 4)
    figures["warm_plan_cpu_s"] = round(statistics.median(warm), 4)
    figures["first_to_warm"] = round(statistics.median(
        [f / w for f, w in zip(first, warm, strict=True)]), 2)
    print(f"medians of {a.repeats} fresh processes (CPU: user + system of the process)")
    for name in ("help", "plan"):
        f = figures[name]
        print(f"  rrtcolearn {name:<5} wall {f['wall_s']:6.3f} s  CPU {f['cpu_s']:6.3f} s  "
              f"peak RSS {f['peak_rss_mb']:5.0f} MB  (walls {f['wall_s_all']})")
    print(f"  planning CPU: first query {figures['first_plan_cpu_s']:.4f} s, warm "
          f"{figures['warm_plan_cpu_s']:.4f} s, ratio {figures['first_to_warm']:.2f}")
    figures["systems"] = [system_plan(cli, run, a.iterations, a.repeats)
                          for run in a.systems]
    for f in figures["systems"]:
        print(f"  plan {f['run']} ({a.iterations} iterations): wall {f['wall_s']:.3f} s, "
              f"CPU {f['cpu_s']:.3f} s (planning {f['planning_cpu_s']:.3f} s, the rest "
              f"{f['rest_cpu_s']:.3f} s), peak RSS {f['peak_rss_mb']:.0f} MB, functions.npz "
              f"{f['functions_mb']:.1f} MB: <= {WALL_TARGET_S:g} s and <= "
              f"{RSS_TARGET_MB:g} MB {'met' if f['meets_targets'] else 'NOT met'} "
              f"(walls {f['wall_s_all']})")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
