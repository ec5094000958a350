"""Soak: consecutive plan queries in one process; memory must not grow.

    python bench/soak.py [--queries 10000]

`make bench` runs 1 000 of them, this script 10 000 by default. Tolerance 0.2 keeps a query
short (10 000 took about a minute and a half on the README's faster machine, 500 took
33 s of CPU on a slower one); each query has its own seed. Resident memory is read from
/proc (current) and getrusage (peak) after a warm-up of 100 queries and at the end.
"""

from __future__ import annotations

import json
import resource
import time

import numpy as np

from rrtcolearn.config import Config
from rrtcolearn.data.clean import clean_data
from rrtcolearn.data.generate import generate_data
from rrtcolearn.pipeline import FittedModel, fit_functions, plan, resolve
from rrtcolearn.systems import make

QUERIES = 10_000
WARMUP = 100


def rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * resource.getpagesize() / 2**20


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main(queries: int = QUERIES) -> dict:
    system = make("pendulum")
    cfg = resolve(Config(), system)  # the library's defaults, derived
    data, _ = generate_data(system, 1, cfg.generate.n_simulations, max_cost=cfg.max_cost)
    cleaned, _ = clean_data(data, seed=1)
    del data
    model = FittedModel(system, cfg, fit_functions(system, cleaned, cfg),
                        float(cleaned.duration.max()), 1.5)
    failures = unsolved = 0
    start = {}
    t0 = time.process_time()
    for q in range(queries):
        if q == WARMUP:
            start = {"rss": rss_mib(), "peak": peak_mib()}
        try:
            p = plan(model, [-np.pi, 0], [0, 0], 0.2, seed=q, time_limit=10.0)
            unsolved += not p.solved
        except Exception:
            failures += 1
    cpu = time.process_time() - t0
    return {
        "soak_queries": queries,
        "soak_failures": failures,
        "soak_unsolved": unsolved,
        "soak_rss_mib_start": round(start["rss"], 1),
        "soak_rss_mib_end": round(rss_mib(), 1),
        "soak_peak_rss_mib_start": round(start["peak"], 1),
        "soak_peak_rss_mib_end": round(peak_mib(), 1),
        "soak_cpu_s": round(cpu, 1),
    }


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=QUERIES)
    print(json.dumps(main(ap.parse_args().queries)))
