"""Chunked, seeded execution: identical results for every backend and worker count, resume."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import distributed  # an extra: `make test` installs it; missing, the suite fails
import numpy as np
import pytest

from rrtcolearn.config import load_config
from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import digest, load_dataset
from rrtcolearn.parallel import ExecutionSettings
from rrtcolearn.pipeline import generate, inspect_run


def same(a, b) -> bool:
    return digest(a.arrays()) == digest(b.arrays())


@pytest.fixture(scope="module")
def serial(pendulum):
    return generate_data(pendulum, 21, 3000, chunk_size=250)[0]


@pytest.mark.parametrize("workers", [1, 2, 4])
def test_process_workers_do_not_change_the_data(pendulum, serial, workers):
    settings = ExecutionSettings("processes" if workers > 1 else "serial", workers)
    data, _ = generate_data(pendulum, 21, 3000, chunk_size=250, settings=settings)
    assert same(data, serial)


def test_dask_local_cluster_gives_the_same_data(pendulum, serial):
    data, _ = generate_data(pendulum, 21, 3000, chunk_size=250,
                            settings=ExecutionSettings("dask", 2))
    assert same(data, serial)


def test_a_killed_dask_worker_costs_only_its_chunk(pendulum, serial):
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        pids = list(client.run(os.getpid).values())
        killed = []

        def kill_one(_count: int) -> None:
            if not killed:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])

        data, _ = generate_data(pendulum, 21, 3000, chunk_size=250, progress=kill_one,
                                settings=ExecutionSettings("dask", 2, cluster.scheduler_address))
    assert killed
    assert same(data, serial)


def test_generate_resumes_after_sigkill(tmp_path: Path):
    # 240 chunks of 250 simulations: killed after 20, far from done
    args = ["--set", "generate.n_simulations=60000", "--set", "generate.chunk_size=250",
            "--seed", "5"]
    exe = str(Path(sys.executable).with_name("rrtcolearn"))
    out = tmp_path / "killed"
    proc = subprocess.Popen([exe, "generate", "--out", str(out), *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    shards = out / "shards" / "generate"
    deadline = time.time() + 120
    while time.time() < deadline and len(list(shards.glob("chunk-*.npz"))) < 20:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = len(list(shards.glob("chunk-*.npz")))
    assert 0 < finished < 240, "the kill must land in the middle of the run"
    assert not (out / "dataset.npz").exists()
    cfg = load_config(overrides=["generate.n_simulations=60000", "generate.chunk_size=250"])
    cfg = cfg.model_copy(update={"seed": 5})
    resumed, stats = generate(cfg, out)
    assert stats.resumed_chunks >= finished
    assert not shards.exists() and not shards.parent.exists()
    fresh, _ = generate(cfg, tmp_path / "fresh")
    assert same(resumed, fresh)
    digests = {r["file"]: r["sha256"] for r in inspect_run(out)}
    assert digests["dataset.npz"] == {r["file"]: r["sha256"]
                                      for r in inspect_run(tmp_path / "fresh")}["dataset.npz"]


def test_finished_dataset_is_not_recomputed(tmp_path: Path):
    cfg = load_config(overrides=["generate.n_simulations=500"])
    data, _ = generate(cfg, tmp_path)
    mtime = (tmp_path / "dataset.npz").stat().st_mtime_ns
    again, _ = generate(cfg, tmp_path)
    assert (tmp_path / "dataset.npz").stat().st_mtime_ns == mtime
    assert np.array_equal(again.x1, data.x1)
    other = cfg.model_copy(update={"seed": 1})
    changed, _ = generate(other, tmp_path)
    assert not np.array_equal(changed.x1[:5], data.x1[:5])
    assert load_dataset(tmp_path / "dataset.npz")[1]["config"]["seed"] == 1


@pytest.mark.parametrize("chunk_size", [1, 97, 3000])
def test_chunking_does_not_change_the_data(pendulum, serial, chunk_size):
    data, _ = generate_data(pendulum, 21, 3000, chunk_size=chunk_size)
    assert same(data, serial)
