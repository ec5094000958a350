"""When a planner must stop: a time limit, an iteration limit, or both."""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass
class TerminationCondition:
    """Stops after ``time_limit`` seconds of wall time, ``cpu_time_limit`` seconds of this
    process's CPU time, or ``max_iterations`` iterations, whichever comes first."""

    time_limit: float | None = 10.0
    max_iterations: int | None = None
    cpu_time_limit: float | None = None
    _start: float = field(default=0.0, init=False)
    _cpu_start: float = field(default=0.0, init=False)

    def start(self) -> None:
        self._start = time.perf_counter()
        self._cpu_start = time.process_time()

    def elapsed(self) -> float:
        return time.perf_counter() - self._start

    def __call__(self, iterations: int) -> bool:
        if self.max_iterations is not None and iterations >= self.max_iterations:
            return True
        if self.cpu_time_limit is not None and \
                time.process_time() - self._cpu_start >= self.cpu_time_limit:
            return True
        return self.time_limit is not None and self.elapsed() >= self.time_limit
