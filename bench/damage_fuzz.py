"""Random damage to an artefact file: every damaged copy is refused with the one-line
`ArtefactError` or loads byte-identical to the original.

The artefact (``--artefact``): a tiny pendulum ``dataset`` (``--simulations`` simulations,
seeded; `save_dataset` / `load_dataset`), the ``model`` fitted on it (`LearnedFunctions.save`
/ `LearnedFunctions.load`, the learned-functions .npz of a run) or a ``plan`` file planned with
that model (`write_plan` / `read_plan`, checked JSON). Each trial damages its bytes in one of
four ways, drawn in turn from a seeded generator: ``flip`` (1-4 bytes XORed with a random
non-zero byte), ``truncate`` (cut at a random length), ``garbage`` (up to 300 random bytes,
half of them behind a zip local-file signature so the loader gets past its first check) and
``append`` (1-50 random bytes after the end). The damaged bytes are written to a file on tmpfs
(``/dev/shm`` where it exists) and loaded. Outcomes: ``refused`` (ArtefactError, one line),
``identical`` (loaded, and its content equal to the original's: every array in dtype, shape
and bytes and the header, or the whole plan document) and the failures
``accepted-different`` and ``raised <type>`` (anything else escaping the loader), each failure
printed with its trial number and damage so it can be replayed.

    python bench/damage_fuzz.py [--artefact dataset] [--trials 100000] [--seed 0]
                                [--simulations 10]

Prints counts per kind and outcome, the CPU time, and last one JSON line; exits 1 if any
trial failed. 100 000 trials of the dataset take under a minute of CPU.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rrtcolearn.config import load_config
from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import load_dataset, save_dataset
from rrtcolearn.errors import ArtefactError
from rrtcolearn.learn import LearnedFunctions
from rrtcolearn.pipeline import FittedModel, fit_functions, plan, read_plan, write_plan
from rrtcolearn.systems import make

KINDS = ("flip", "truncate", "garbage", "append")


def damage(raw: bytes, kind: str, rng: np.random.Generator) -> tuple[bytes, str]:
    """``raw`` damaged one way, and a short description of the damage (to replay it)."""
    b = bytearray(raw)
    if kind == "flip":
        done = []
        for _ in range(int(rng.integers(1, 5))):
            i, x = int(rng.integers(len(b))), int(rng.integers(1, 256))
            b[i] ^= x
            done.append(f"{i}^{x}")
        return bytes(b), "flip " + ",".join(done)
    if kind == "truncate":
        n = int(rng.integers(len(b)))
        return bytes(b[:n]), f"truncate {n}"
    if kind == "garbage":
        junk = rng.bytes(int(rng.integers(301)))
        if rng.random() < 0.5:
            junk = b"PK\x03\x04" + junk
        return junk, f"garbage {junk[:16].hex()}... ({len(junk)} bytes)"
    tail = rng.bytes(int(rng.integers(1, 51)))
    return bytes(b) + tail, f"append {len(tail)} bytes"


def _arrays(load_file):
    """A loader returning (arrays, header) of an .npz artefact after ``load_file`` read it."""
    def load(path: Path):
        _, meta = load_file(path)  # the artefact's own loader: what a user's command runs
        with np.load(path, allow_pickle=False) as npz:  # it accepted: then read what it read
            return {k: npz[k] for k in npz.files}, meta
    return load


def artefact(kind: str, simulations: int, workdir: Path) -> tuple[Callable, bytes]:
    """(loader, original bytes) of a freshly made artefact of ``kind``."""
    system = make("pendulum")
    data, _ = generate_data(system, 7, simulations, chunk_size=simulations)
    path = workdir / "original"
    if kind == "dataset":
        save_dataset(path, data, {"system": "pendulum"})
        return _arrays(load_dataset), path.read_bytes()
    config = load_config(overrides=["learn.learner='knn'", "learn.validity_threshold=0.5"])
    functions = fit_functions(system, data, config)
    if kind == "model":
        functions.save(path, {"system": "pendulum"})
        return _arrays(LearnedFunctions.load), path.read_bytes()
    model = FittedModel(system, config, functions, float(data.duration.max()),
                        config.generate.max_state_distance)
    write_plan(plan(model, [-np.pi, 0.0], [0.0, 0.0], 0.3, 0, time_limit=None,
                    max_iterations=50), path)
    return read_plan, path.read_bytes()


def same(a, b) -> bool:
    """Equal content: plan documents equal; arrays equal in dtype, shape and bytes, and
    headers equal."""
    if isinstance(a, dict):
        return a == b
    (arrays, meta), (arrays0, meta0) = a, b
    return meta == meta0 and arrays.keys() == arrays0.keys() and all(
        arrays[k].dtype == arrays0[k].dtype and arrays[k].shape == arrays0[k].shape
        and arrays[k].tobytes() == arrays0[k].tobytes() for k in arrays0)


def trials(args: argparse.Namespace, workdir: Path
           ) -> tuple[Counter[tuple[str, str]], int, float, bytes]:
    """Run the trials in ``workdir``: counts per (kind, outcome), failures, CPU seconds and
    the original bytes."""
    load, raw = artefact(args.artefact, args.simulations, workdir)
    target = workdir / "damaged"
    target.write_bytes(raw)
    original = load(target)
    print(f"{args.artefact}: {len(raw)} bytes; {args.trials} trials, seed {args.seed}; "
          f"files in {workdir}")

    rng = np.random.default_rng(args.seed)
    counts: Counter[tuple[str, str]] = Counter()
    failures = 0
    cpu0 = time.process_time()
    for trial in range(args.trials):
        kind = KINDS[trial % len(KINDS)]
        damaged, what = damage(raw, kind, rng)
        target.write_bytes(damaged)
        try:
            content = load(target)
        except ArtefactError as exc:
            outcome = "refused" if "\n" not in str(exc) else "refused over several lines"
            detail = str(exc)
        except Exception as exc:  # what escapes the loader is the finding
            outcome = f"raised {type(exc).__name__}"
            detail = str(exc)
        else:
            outcome = "identical" if same(content, original) else "accepted-different"
            detail = ""
        counts[kind, outcome] += 1
        if outcome not in ("refused", "identical"):
            failures += 1
            if failures <= 20:
                print(f"FAIL trial {trial}: {what}: {outcome} {detail}"[:300])
    return counts, failures, time.process_time() - cpu0, raw


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--artefact", choices=("dataset", "model", "plan"), default="dataset")
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--simulations", type=int, default=10)
    args = ap.parse_args(argv)

    shm = Path("/dev/shm")
    workdir = Path(tempfile.mkdtemp(dir=shm if shm.is_dir() else None, prefix="damage-fuzz-"))
    try:
        counts, failures, cpu, raw = trials(args, workdir)
    finally:
        shutil.rmtree(workdir)

    outcomes = sorted({o for _, o in counts})
    print(f"\n{'kind':<10}" + "".join(f"{o:>22}" for o in outcomes))
    for kind in KINDS:
        print(f"{kind:<10}" + "".join(f"{counts[kind, o]:>22}" for o in outcomes))
    print(f"\n{args.trials} trials, {failures} failures, {cpu:.1f} s CPU")
    print(json.dumps({"artefact": args.artefact, "trials": args.trials, "seed": args.seed,
                      "bytes": len(raw),
                      "failures": failures, "cpu_s": round(cpu, 1),
                      "counts": {f"{k}/{o}": n for (k, o), n in sorted(counts.items())}}))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
