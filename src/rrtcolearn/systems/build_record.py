"""Build records: the package's own systems rebuilt from their generated modules, without sympy.

Building a system from its sympy definition (`rrtcolearn.systems.symbolic.build_system`)
imports sympy, derives Pontryagin's equations and prints the kernels: a quarter of a second
before a plan can start. What that build produces is a function of its inputs only: the
definition's code, the code that derives and prints it, and the versions of sympy, mpmath,
numpy and Python. A build record stores, under a key hashed from all of these, the SHA-256 of
the generated module and the system's plain fields (names, boxes, defaults); a later process
with the same key imports that module (its text checked against the digest) and rebuilds the
same `SymbolicSystem` without sympy. Its ``derivation`` and ``parametrisation`` are then
derived again from its ``definition`` only when asked for (`SymbolicSystem.symbolic`, e.g.
to change its input limits). A system with configured input limits (`with_input_limits` of
the definition's system) has a record of its own, the limits being part of the key.

The key covers every source file of `rrtcolearn.systems` (the definitions, the derivation,
the code generation) and `rrtcolearn.integrate` (the kernels compiled into every generated
module), so an edit to any of them, or another sympy, misses every record and builds afresh;
a stale module is never used. A record is written only when the system rebuilt from it
equals the one just built, field by field. Records are JSON files beside the generated
modules (``rrtcolearn_build_<key>.json``); nothing is unpickled or evaluated. Only the
package's own definitions have records: a user's definition may depend on anything.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import sys
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from rrtcolearn.systems.generated import (
    _GENERATED,
    _MODULE_PREFIX,
    SymbolicSystem,
    _is_generated,
    _write_atomic,
    direction_from_costate,
    generated_dir,
    load_generated_module,
)

__all__ = ["build", "record_key"]

RECORD_FORMAT = "rrtcolearn.build-record"
RECORD_SCHEMA = 1
_RECORD_PREFIX = "rrtcolearn_build_"
# fields a record does not store: the module's text (its digest instead), the sympy objects
# (derived again on demand) and the definition (the caller's)
_NOT_STORED = ("source", "derivation", "parametrisation", "definition")
_FUNCTIONS = {"direction_from_costate": direction_from_costate}


def _key_files() -> list[Path]:
    """The source files a shipped system's build depends on."""
    systems = Path(__file__).parent
    return [*sorted(systems.glob("*.py")), systems.parent / "integrate.py"]


def _limits_text(input_limits: tuple | None) -> str:
    """The limits exactly (float.hex), or that the definition's own are kept."""
    if input_limits is None:
        return "the definition's own input limits"
    return " ".join("none" if side is None else
                    ",".join(float(v).hex() for v in np.ravel(side)) for side in input_limits)


def record_key(definition: Callable, input_limits: tuple | None = None) -> str | None:
    """SHA-256 of everything the build of ``definition`` (with ``input_limits``, a (low, high)
    pair for `with_input_limits`) depends on (module docstring); None when a version cannot
    be read or ``definition`` is not a named function (no record is then used or written)."""
    name = getattr(definition, "__qualname__", None)
    if name is None:
        return None
    h = hashlib.sha256(f"{RECORD_FORMAT} {RECORD_SCHEMA}\n".encode())
    h.update(f"{definition.__module__}:{name}\n{_limits_text(input_limits)}\n".encode())
    try:
        versions = [version(p) for p in ("sympy", "mpmath")]
    except PackageNotFoundError:
        return None
    h.update(f"{versions} {np.__version__} {sys.version}\n".encode())
    for path in _key_files():
        h.update(f"{path.name} {path.stat().st_size}\n".encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _record_path(key: str, cache_dir: str | os.PathLike | None) -> Path:
    return generated_dir(cache_dir) / f"{_RECORD_PREFIX}{key}.json"


def _plain(value: Any) -> bool:
    """Whether ``value`` survives a JSON round trip unchanged (finite floats, no tuples)."""
    try:
        return json.loads(json.dumps(value, allow_nan=False)) == value
    except (TypeError, ValueError):
        return False


def _encode(system: SymbolicSystem) -> dict | None:
    """The record's fields of ``system``, or None if one of them cannot be recorded."""
    digest = hashlib.sha256(system.source.encode("utf-8")).hexdigest()
    modname = _MODULE_PREFIX + digest
    out = {}
    for f in dataclasses.fields(system):
        if f.name in _NOT_STORED:
            continue
        value = getattr(system, f.name)
        attr = _GENERATED.get(f.name)
        name = next((k for k, v in _FUNCTIONS.items() if v is value), None)
        if attr is not None and value is not None and _is_generated(value, modname, attr):
            out[f.name] = {"generated": attr}
        elif name is not None:
            out[f.name] = {"function": name}
        elif isinstance(value, np.ndarray) and value.dtype == np.float64:
            # float.hex: exact, and infinite limits too
            out[f.name] = {"array": [float(v).hex() for v in value.ravel()],
                           "shape": list(value.shape)}
        elif isinstance(value, tuple) and _plain(list(value)):
            out[f.name] = {"tuple": list(value)}
        elif _plain(value):
            out[f.name] = {"value": value}
        else:
            return None
    return {"format": RECORD_FORMAT, "schema_version": RECORD_SCHEMA, "module": digest,
            "fields": out}


def _decode(record: dict, definition: Callable, cache_dir: str | os.PathLike | None
            ) -> SymbolicSystem | None:
    """The system of a record, or None if the record or its module does not check out."""
    if record.get("format") != RECORD_FORMAT or record.get("schema_version") != RECORD_SCHEMA:
        return None
    digest = record.get("module")
    if not isinstance(digest, str):
        return None
    path = generated_dir(cache_dir) / f"{_MODULE_PREFIX}{digest}.py"
    try:
        source = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    if hashlib.sha256(source.encode("utf-8")).hexdigest() != digest:
        return None  # not the module the record was made with
    module = load_generated_module(source, cache_dir)
    kwargs: dict[str, Any] = {}
    names = {f.name for f in dataclasses.fields(SymbolicSystem)} - set(_NOT_STORED)
    fields = record.get("fields")
    if not isinstance(fields, dict) or set(fields) != names:
        return None
    for name, entry in fields.items():
        kind, value = next(iter(entry.items())) if isinstance(entry, dict) and entry else \
            (None, None)
        if kind == "generated" and value in _GENERATED.values():
            kwargs[name] = getattr(module, value)
        elif kind == "function" and value in _FUNCTIONS:
            kwargs[name] = _FUNCTIONS[value]
        elif kind == "array":
            kwargs[name] = np.array([float.fromhex(v) for v in value],
                                    dtype=np.float64).reshape(entry["shape"])
        elif kind == "tuple":
            kwargs[name] = tuple(value)
        elif kind == "value":
            kwargs[name] = value
        else:
            return None
    return SymbolicSystem(**kwargs, source=source, definition=definition)


def _same(a: SymbolicSystem, b: SymbolicSystem) -> bool:
    """Whether two systems agree in every field a record stores, and in their source."""
    for f in dataclasses.fields(a):
        if f.name in ("derivation", "parametrisation", "definition"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (isinstance(x, np.ndarray) and isinstance(y, np.ndarray)
                    and x.dtype == y.dtype and np.array_equal(x, y)):
                return False
        elif not (x is y or (type(x) is type(y) and x == y)):
            return False
    return True


def _limited(definition: Callable[[], SymbolicSystem], low, high) -> SymbolicSystem:
    from rrtcolearn.systems.symbolic import with_input_limits

    return with_input_limits(definition(), low, high)


def build(definition: Callable[[], SymbolicSystem], input_limits: tuple | None = None,
          cache_dir: str | os.PathLike | None = None) -> SymbolicSystem:
    """``definition()`` (with ``input_limits``: ``with_input_limits(definition(), *input_limits)``),
    rebuilt from its build record when one matches (no sympy), else built and recorded for the
    next process. The system's ``definition`` is what builds it again with sympy."""
    full = definition if input_limits is None else \
        functools.partial(_limited, definition, *input_limits)
    key = record_key(definition, input_limits)
    if key is None:
        return full()
    path = _record_path(key, cache_dir)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        record = None
    if isinstance(record, dict):
        try:
            system = _decode(record, full, cache_dir)
        except (KeyError, TypeError, ValueError, AttributeError):
            system = None
        if system is not None:
            return system
    system = full()
    if not isinstance(system, SymbolicSystem):
        return system
    system = dataclasses.replace(system, definition=full)
    if system.source:
        record = _encode(system)
        if record is not None and (again := _decode(record, full, cache_dir)) is not None \
                and _same(system, again):
            try:
                _write_atomic(path, json.dumps(record, indent=1, allow_nan=False) + "\n")
            except OSError:  # an unwritable cache: the next process builds again
                pass
    return system
