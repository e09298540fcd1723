"""Validation of model parameters: errors name the class, the field and the reason."""

from __future__ import annotations

import math


def _value(obj, name: str) -> float:
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
        raise ValueError(f"{type(obj).__name__}.{name} must be a number, got {v!r}")
    return float(v)


def non_negative(obj, *names: str) -> None:
    for n in names:
        if _value(obj, n) < 0:
            raise ValueError(f"{type(obj).__name__}.{n} must be >= 0, got {getattr(obj, n)!r}")


def positive(obj, *names: str) -> None:
    for n in names:
        if not _value(obj, n) > 0:
            raise ValueError(f"{type(obj).__name__}.{n} must be > 0, got {getattr(obj, n)!r}")


def probability(obj, *names: str) -> None:
    for n in names:
        if not 0.0 <= _value(obj, n) <= 1.0:
            raise ValueError(f"{type(obj).__name__}.{n} must be in [0, 1], got {getattr(obj, n)!r}")


def ordered(obj, low: str, high: str) -> None:
    if _value(obj, low) > _value(obj, high):
        raise ValueError(f"{type(obj).__name__}: {low} must not exceed {high}")
