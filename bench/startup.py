"""Start-up of the command line: what one `rrtcolearn plan` costs in a fresh process.

Prints, as medians over fresh processes (``--repeats``, default 5):

- wall and CPU time (user + system, of the child process) of ``rrtcolearn --help``;
- wall and CPU time of ``rrtcolearn plan`` for the pendulum's swing-up query
  (``--start=-3.14159,0 --goal 0,0 --goal-tolerance 0.1 --seed 1``);
- the planning CPU of the first query of a fresh process after `pipeline.load_model`, of
  the same query planned again in that process (warm), and their ratio;

then one JSON object with the same figures as its last line. The commands run as
``python -m rrtcolearn.cli`` with this interpreter and the current ``PYTHONPATH``, so
``PYTHONPATH=<checkout>/src python bench/startup.py`` measures another checkout. The model is
``--model RUN_DIR`` (default ``runs/pendulum-swingup``), made with ``rrtcolearn run --out
RUN_DIR`` first if it holds none. Figures, not assertions: the machine may be shared.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
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


def timed_process(args: list[str]) -> tuple[float, float, str]:
    """(wall s, CPU s of the child, its stdout) of one fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(args)}\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, proc.stdout


def medians(args: list[str], repeats: int) -> dict:
    runs = [timed_process(args)[:2] for _ in range(repeats)]
    walls, cpus = zip(*runs, strict=True)
    return {"wall_s": round(statistics.median(walls), 3),
            "cpu_s": round(statistics.median(cpus), 3),
            "wall_s_all": [round(w, 3) for w in walls]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=Path("runs/pendulum-swingup"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warm", type=int, default=5, help="warm plans per process")
    a = ap.parse_args()
    cli = [sys.executable, "-m", "rrtcolearn.cli"]
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
              f"(walls {f['wall_s_all']})")
    print(f"  planning CPU: first query {figures['first_plan_cpu_s']:.4f} s, warm "
          f"{figures['warm_plan_cpu_s']:.4f} s, ratio {figures['first_to_warm']:.2f}")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
