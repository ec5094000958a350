"""Random damage to a dataset file: every damaged copy is refused with the one-line
`ArtefactError` or loads byte-identical to the original.

A tiny pendulum dataset (``--simulations`` simulations, seeded) is saved with
`save_dataset`; each trial damages its bytes in one of four ways, drawn in turn from a seeded
generator: ``flip`` (1-4 bytes XORed with a random non-zero byte), ``truncate`` (cut at a
random length), ``garbage`` (up to 300 random bytes, half of them behind a zip local-file
signature so the loader gets past its first check) and ``append`` (1-50 random bytes after
the end). The damaged bytes are written to a file on tmpfs (``/dev/shm`` where it exists) and
loaded with `load_dataset`. Outcomes: ``refused`` (ArtefactError, one line), ``identical``
(loaded; every array equal in dtype, shape and bytes to the original's, header equal) and
the failures ``accepted-different`` and ``raised <type>`` (anything else escaping the loader),
each failure printed with its trial number and damage so it can be replayed.

    python bench/damage_fuzz.py [--trials 100000] [--seed 0] [--simulations 10]

Prints counts per kind and outcome, the CPU time, and last one JSON line; exits 1 if any
trial failed. 100 000 trials take a few CPU minutes.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from rrtcolearn.data.generate import generate_data
from rrtcolearn.data.store import DATASET_FORMAT, load_arrays, load_dataset, save_dataset
from rrtcolearn.errors import ArtefactError
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--simulations", type=int, default=10)
    args = ap.parse_args(argv)

    shm = Path("/dev/shm")
    workdir = Path(tempfile.mkdtemp(dir=shm if shm.is_dir() else None, prefix="damage-fuzz-"))
    original_path, target = workdir / "original.npz", workdir / "damaged.npz"
    data, _ = generate_data(make("pendulum"), 7, args.simulations, chunk_size=args.simulations)
    save_dataset(original_path, data, {"system": "pendulum"})
    raw = original_path.read_bytes()
    original, original_meta = load_arrays(original_path, DATASET_FORMAT)
    print(f"dataset: {len(data)} rows, {len(raw)} bytes; {args.trials} trials, "
          f"seed {args.seed}; files in {workdir}")

    rng = np.random.default_rng(args.seed)
    counts: Counter[tuple[str, str]] = Counter()
    failures = 0
    cpu0 = time.process_time()
    for trial in range(args.trials):
        kind = KINDS[trial % len(KINDS)]
        damaged, what = damage(raw, kind, rng)
        target.write_bytes(damaged)
        try:
            load_dataset(target)
            arrays, meta = load_arrays(target, DATASET_FORMAT)
        except ArtefactError as exc:
            outcome = "refused" if "\n" not in str(exc) else "refused over several lines"
            detail = str(exc)
        except Exception as exc:  # what escapes the loader is the finding
            outcome = f"raised {type(exc).__name__}"
            detail = str(exc)
        else:
            same = meta == original_meta and arrays.keys() == original.keys() and all(
                arrays[k].dtype == original[k].dtype and arrays[k].shape == original[k].shape
                and arrays[k].tobytes() == original[k].tobytes() for k in original)
            outcome = "identical" if same else "accepted-different"
            detail = ""
        counts[kind, outcome] += 1
        if outcome not in ("refused", "identical"):
            failures += 1
            if failures <= 20:
                print(f"FAIL trial {trial}: {what}: {outcome} {detail}"[:300])
    cpu = time.process_time() - cpu0
    for f in workdir.iterdir():
        f.unlink()
    os.rmdir(workdir)

    outcomes = sorted({o for _, o in counts})
    print(f"\n{'kind':<10}" + "".join(f"{o:>22}" for o in outcomes))
    for kind in KINDS:
        print(f"{kind:<10}" + "".join(f"{counts[kind, o]:>22}" for o in outcomes))
    print(f"\n{args.trials} trials, {failures} failures, {cpu:.1f} s CPU")
    print(json.dumps({"trials": args.trials, "seed": args.seed, "bytes": len(raw),
                      "failures": failures, "cpu_s": round(cpu, 1),
                      "counts": {f"{k}/{o}": n for (k, o), n in sorted(counts.items())}}))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
