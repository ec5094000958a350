"""Physical parameters of the shipped systems, overridable by name (a system "like the
model, with other masses and lengths": the truth a tracked plan is tested against)."""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["with_parameters"]


def with_parameters(defaults: Mapping, overrides: Mapping[str, float] | None) -> dict:
    """``defaults`` (sympy symbol -> value) with the values of ``overrides`` (symbol name ->
    value) in their place; ValueError naming an unknown name."""
    by_name = {str(symbol): symbol for symbol in defaults}
    unknown = sorted(set(overrides or {}) - set(by_name))
    if unknown:
        raise ValueError(f"unknown parameters {unknown}; this system's are "
                         f"{sorted(by_name)}")
    out = dict(defaults)
    for name, value in (overrides or {}).items():
        out[by_name[name]] = float(value)
    return out
