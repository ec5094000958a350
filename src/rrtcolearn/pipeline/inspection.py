"""What a run cost and holds: the CPU time of a step, and the size and content digest of
every artefact of a run directory (`rrtcolearn inspect`)."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from rrtcolearn.config import read_toml
from rrtcolearn.data.store import digest, load_arrays, load_dataset, read_json
from rrtcolearn.learn.models import FUNCTIONS_FORMAT
from rrtcolearn.pipeline.layout import FUNCTIONS_FILE, existing_run_dir


def timed(fn, *args, **kwargs):
    """(result, CPU seconds of this process). Worker processes are kept between calls, so
    their CPU is reported by the work itself (``GenerationStats.worker_cpu_s``)."""
    t0 = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - t0


_TIMING_KEYS = {"planning_time_s", "planning_cpu_s", "wall_s", "generate_cpu_s", "clean_cpu_s",
                "fit_cpu_s", "offline_cpu_s"}


def content_digest(path: str | Path) -> tuple[str, str]:
    """(kind, SHA-256) of an artefact's content, independent of chunking and file layout.

    Datasets: the expanded arrays (x0, x1, cost, params, duration, costate, simulation) in
    name order; fitted functions: their arrays; JSON and TOML: the canonical JSON of their
    content without timing fields; anything else: the file's bytes.
    """
    path = Path(path)
    if path.name == FUNCTIONS_FILE:
        arrays, _ = load_arrays(path, FUNCTIONS_FORMAT)
        return "functions", digest(arrays)
    if path.suffix == ".npz":
        data, _ = load_dataset(path)
        return "dataset", digest(data.arrays())
    if path.suffix in (".json", ".toml"):
        content = read_json(path) if path.suffix == ".json" else read_toml(path)
        if isinstance(content, dict):
            content = {k: v for k, v in content.items() if k not in _TIMING_KEYS}
        canon = json.dumps(content, sort_keys=True, separators=(",", ":"))
        return path.suffix[1:], hashlib.sha256(canon.encode()).hexdigest()
    return "file", hashlib.sha256(path.read_bytes()).hexdigest()


def inspect_run(run_dir: str | Path) -> list[dict]:
    """Size and content digest of every artefact in a run directory."""
    run_dir = existing_run_dir(run_dir)
    rows = []
    for path in sorted(p for p in run_dir.iterdir() if p.is_file()
                       and not p.name.startswith(".")):
        kind, sha = content_digest(path)
        rows.append({"file": path.name, "kind": kind, "bytes": path.stat().st_size,
                     "sha256": sha})
    return rows
