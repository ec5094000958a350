"""Generation throughput with 1 and 2 local worker processes (part of `make bench`).

A 400000-simulation pendulum run (chunks of 2000) on the processes backend, with the worker
pool started before the clock runs (it is kept between calls); wall time gives the speed-up,
CPU time (the parent's plus the workers' own, reported per chunk) the throughput per CPU
second. Medians of 3 repeats. Prints one JSON line.
"""

from __future__ import annotations

import json
import statistics
import time

from rrtcolearn.data.generate import generate_data
from rrtcolearn.parallel import ExecutionSettings
from rrtcolearn.systems import make

N = 400_000
REPEATS = 3


def measure(workers: int) -> tuple[float, float]:
    system = make("pendulum")
    settings = ExecutionSettings("processes", workers)
    walls, cpus = [], []
    for r in range(REPEATS):
        c0, w0 = time.process_time(), time.perf_counter()
        _, stats = generate_data(system, r, N, settings=settings)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0 + stats.worker_cpu_s)
    return statistics.median(walls), statistics.median(cpus)


def main() -> dict:
    for workers in (1, 2):  # start the pools and load the compiled kernels in the workers
        generate_data(make("pendulum"), 0, 8000, settings=ExecutionSettings("processes",
                                                                             workers))
    w1, c1 = measure(1)
    w2, c2 = measure(2)
    result = {
        "gen_sims_per_cpu_s_1w": round(N / c1),
        "gen_sims_per_cpu_s_2w": round(N / c2),
        "gen_wall_s_1w": round(w1, 3),
        "gen_wall_s_2w": round(w2, 3),
        "gen_speedup_2w": round(w1 / w2, 3),
        "gen_parallel_efficiency_2w": round(w1 / w2 / 2, 3),
    }
    return result


if __name__ == "__main__":
    print(json.dumps(main()))
