"""The run directory: the names of the files the steps write, and its configuration file.

Run directory layout::

    config.toml     resolved configuration of the last step run here
    dataset.npz     raw data (Alg. 2)
    colearn.json    the co-learning rounds, when there were any
    cleaned.npz     cleaned data (Alg. 3)
    model.json      learner parameters; models are rebuilt from cleaned.npz (no pickle)
    functions.npz   the fitted functions' arrays (checksum in model.json)
    plan.json       the plan of the swing-up query, plan.png its tree (paper Fig. 2)
    summary.json    figures of the last `run`
"""

from __future__ import annotations

from pathlib import Path

from rrtcolearn.config import Config, read_toml, to_toml, validate
from rrtcolearn.data.store import atomic_write_text
from rrtcolearn.errors import ArtefactError

CONFIG_FILE = "config.toml"
DATASET_FILE = "dataset.npz"
COLEARN_FILE = "colearn.json"
CLEANED_FILE = "cleaned.npz"
MODEL_FILE = "model.json"
FUNCTIONS_FILE = "functions.npz"


def existing_run_dir(run_dir: str | Path) -> Path:
    """``run_dir`` as a Path; ArtefactError unless it is a directory (a file given for one,
    e.g. a plan file or model.json, named as such)."""
    run_dir = Path(run_dir)
    if run_dir.is_file():
        raise ArtefactError(f"{run_dir} is a file, not a run directory: give the directory "
                            f"`rrtcolearn run` or `fit` wrote (it holds {MODEL_FILE})")
    if not run_dir.is_dir():
        raise ArtefactError(f"run directory not found: {run_dir}")
    return run_dir


def read_run_config(run_dir: str | Path) -> Config:
    """The resolved configuration a run directory's last step wrote (``config.toml``)."""
    return validate(read_toml(Path(run_dir) / CONFIG_FILE))


def save_config(config: Config, run_dir: Path) -> None:
    atomic_write_text(Path(run_dir) / CONFIG_FILE, to_toml(config))
