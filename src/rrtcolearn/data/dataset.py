"""The `Dataset`: one row per optimal trajectory segment (x0 -> x1)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class Dataset:
    """Rows b = (x0, x1, cost, params, duration) of paper Section 2, plus provenance.

    x0, x1 : (N, n) start and end states.
    cost : (N,) cost-to-go of the segment (integral of w + u^2/2).
    params : (N, k) costate parameters at the start (pendulum: phi).
    duration : (N,) segment duration in seconds.
    costate : (N, n) costate at the start (derived from x0 and params, kept for checks).
    simulation : (N,) index of the simulation the row came from.
    """

    x0: np.ndarray
    x1: np.ndarray
    cost: np.ndarray
    params: np.ndarray
    duration: np.ndarray
    costate: np.ndarray
    simulation: np.ndarray

    def __len__(self) -> int:
        return int(self.cost.shape[0])

    @property
    def inputs(self) -> np.ndarray:
        """(N, 2n) learning inputs (x0, x1)."""
        return np.hstack([self.x0, self.x1])

    def take(self, index: np.ndarray) -> Dataset:
        """Rows selected by an index or boolean mask."""
        return Dataset(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Dataset:
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if n not in arrays]
        if missing:
            raise ValueError(f"dataset is missing arrays: {', '.join(missing)}")
        n = arrays["cost"].shape[0]
        for name in names:
            if arrays[name].shape[:1] != (n,):
                raise ValueError(f"dataset array {name!r} has {arrays[name].shape[0]} rows, "
                                 f"expected {n}")
        return cls(**{name: arrays[name] for name in names})
