"""The generated system modules and the `System` they back, without sympy.

`rrtcolearn.systems.symbolic` derives a system with sympy and prints its kernels into a
module file named by the SHA-256 of its text; this module writes and imports such files and
defines `SymbolicSystem`, so that a system can be rebuilt from its generated module (a
pickled system in a worker, a system from its build record) without importing sympy.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from rrtcolearn.systems.base import System

__all__ = ["SymbolicSystem", "direction_from_costate", "generated_dir",
           "load_generated_module"]

_MODULE_PREFIX = "rrtcolearn_sys_"


def generated_dir(cache_dir: str | os.PathLike | None = None) -> Path:
    """Directory of the generated system modules: ``$RRTCOLEARN_CACHE/systems`` if that
    variable is set, else ``$XDG_CACHE_HOME/rrtcolearn/systems`` or
    ``~/.cache/rrtcolearn/systems``."""
    if cache_dir is not None:
        root = Path(cache_dir)
    elif os.environ.get("RRTCOLEARN_CACHE"):
        root = Path(os.environ["RRTCOLEARN_CACHE"])
    else:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = (Path(xdg) if xdg else Path.home() / ".cache") / "rrtcolearn"
    return root / "systems"


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".py")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _ensure_file(directory: Path, name: str, source: str) -> Path:
    """The file ``directory/name`` holding ``source``; rewritten only when absent or different
    (rewriting would change its mtime and invalidate numba's cache)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    try:
        if path.read_text(encoding="utf-8") == source:
            return path
    except (OSError, UnicodeDecodeError):
        pass
    _write_atomic(path, source)
    return path


def load_generated_module(source: str, cache_dir: str | os.PathLike | None = None
                          ) -> ModuleType:
    """Import the generated ``source`` from the cache directory, writing it first if needed.

    A module already imported in this process from the same file is reused. When the cache
    directory is not writable a per-user directory under the system temp dir is used instead.
    """
    digest = hashlib.sha256(source.encode("utf-8")).hexdigest()
    modname = _MODULE_PREFIX + digest
    filename = modname + ".py"
    directory = generated_dir(cache_dir)
    try:
        path = _ensure_file(directory, filename, source)
    except OSError as exc:
        fallback = Path(tempfile.gettempdir()) / f"rrtcolearn-{os.getuid()}" / "systems"
        warnings.warn(f"cannot write generated system to {directory} ({exc}); using {fallback}",
                      RuntimeWarning, stacklevel=2)
        path = _ensure_file(fallback, filename, source)
    existing = sys.modules.get(modname)
    if existing is not None and getattr(existing, "__file__", None) == str(path):
        return existing
    spec = importlib.util.spec_from_file_location(modname, path)
    if spec is None or spec.loader is None:  # pragma: no cover - only for exotic filesystems
        raise ImportError(f"cannot import generated module {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(modname, None)
        raise
    return module



# System field -> attribute of the generated module
_GENERATED = {
    "rhs": "rhs",
    "rollout_jit": "rollout_jit",
    "rollout_batch_jit": "rollout_batch_jit",
    "input_max_abs_jit": "input_max_abs",
    "costate_from_params": "costate_from_params",
    "costate_from_params_jit": "costate_from_params_jit",
    "optimal_control": "optimal_control",
    "hamiltonian": "hamiltonian",
    "dynamics": "dynamics",
    "params_from_costate": "params_from_costate",
    "propagate_jit": "propagate_jit",
    "closed_loop_jit": "closed_loop_jit",
    "rollout_draws_jit": "rollout_draws_jit",
    "hold_jit": "hold_jit",
    "explore_jit": "explore_jit",
}


def direction_from_costate(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """The direction parameters (N, n) of costates on H* = 0: lambda / max_i |lambda_i|, in
    [-1, 1]^n (the positive scale on the ray is unique, so the direction determines it)."""
    lam = np.asarray(lam, dtype=np.float64)
    norm = np.abs(lam).max(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return lam / norm


@dataclass(frozen=True)
class _GeneratedRef:
    attr: str


def _is_generated(value: Any, modname: str, attr: str) -> bool:
    """Whether ``value`` is ``attr`` of the generated module ``modname`` (by name, not by
    identity: the module object in ``sys.modules`` may have been re-imported meanwhile)."""
    func = getattr(value, "py_func", value)  # numba dispatchers wrap the Python function
    return (getattr(func, "__module__", None) == modname
            and getattr(func, "__name__", None) == attr)


def _rebuild(cls: type, source: str, state: dict) -> SymbolicSystem:
    module = load_generated_module(source) if source else None
    kwargs = {k: getattr(module, v.attr) if isinstance(v, _GeneratedRef) else v
              for k, v in state.items()}
    return cls(**kwargs)


@dataclass(frozen=True)
class SymbolicSystem(System):
    """A `System` built by `rrtcolearn.systems.symbolic.build_system`, with its generated
    source and derivation.

    It pickles as the source plus its plain fields, so spawned or remote (Dask) workers
    rebuild the module from the source into their own cache; the generated module is not
    importable by name there.
    """

    source: str = field(default="", repr=False, compare=False)
    # a `rrtcolearn.systems.symbolic.Derivation` and `CostateParametrisation` (sympy-backed;
    # not imported here, so that this module needs no sympy)
    derivation: Any = field(default=None, repr=False, compare=False)
    parametrisation: Any = field(default=None, repr=False, compare=False)
    # the function that builds this system from its sympy definition, when the system was
    # rebuilt from its build record without sympy (`rrtcolearn.systems.build_record`):
    # derivation and parametrisation are then None, and `symbolic()` derives them on demand
    definition: Callable[[], SymbolicSystem] | None = field(default=None, repr=False,
                                                            compare=False)

    def symbolic(self) -> tuple[Any, Any]:
        """(derivation, parametrisation), derived again from ``definition`` (with sympy) if
        this system was rebuilt from its build record; (None, None) for a system that has
        neither (not built by `build_system`)."""
        if self.derivation is None and self.definition is not None:
            full = self.definition()
            return full.derivation, full.parametrisation
        return self.derivation, self.parametrisation

    def __reduce__(self):
        digest = hashlib.sha256(self.source.encode("utf-8")).hexdigest()
        modname = _MODULE_PREFIX + digest
        state = {}
        for f in fields(self):
            value = getattr(self, f.name)
            attr = _GENERATED.get(f.name)
            if self.source and attr is not None and _is_generated(value, modname, attr):
                value = _GeneratedRef(attr)
            state[f.name] = value
        return _rebuild, (type(self), self.source, state)
