"""Checks of TOML documents that name the file, the field path and the reason: the scenario
parser's helpers (:mod:`hw_emulation.scenario`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any


class ScenarioError(ValueError):
    """A scenario file is invalid; the message names the file, the field and the reason."""


class Ctx:
    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, path: str, reason: str) -> ScenarioError:
        return ScenarioError(f"{self.source}: {path}: {reason}")

    def number(self, d: dict, key: str, path: str, default: float | None = None, *,
               positive: bool = False, non_negative: bool = False, maximum: float | None = None) -> float:
        if key not in d:
            if default is None:
                raise self.fail(f"{path}.{key}" if path else key, "missing")
            return float(default)
        v = d[key]
        p = f"{path}.{key}" if path else key
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(p, f"must be a finite number, got {v!r}")
        if positive and not v > 0:
            raise self.fail(p, f"must be > 0, got {v!r}")
        if non_negative and v < 0:
            raise self.fail(p, f"must be >= 0, got {v!r}")
        if maximum is not None and v > maximum:
            raise self.fail(p, f"must be at most {maximum:g}, got {v!r}")
        return float(v)

    def string(self, d: dict, key: str, path: str) -> str:
        v = d.get(key)
        if not isinstance(v, str) or not v:
            raise self.fail(f"{path}.{key}" if path else key, f"must be a non-empty string, got {v!r}")
        return v

    def table(self, d: dict, key: str, path: str, required: bool = False) -> dict:
        v = d.get(key, None)
        if v is None:
            if required:
                raise self.fail(f"{path}.{key}" if path else key, "missing")
            return {}
        if not isinstance(v, dict):
            raise self.fail(f"{path}.{key}" if path else key, "must be a table")
        return v

    def model(self, cls, d: dict, path: str, base=None):
        base = base if base is not None else cls()
        names = {f.name for f in dataclasses.fields(cls)}
        for k in d:
            if k not in names:
                raise self.fail(f"{path}.{k}", f"unknown field (known: {', '.join(sorted(names))})")
        try:
            return dataclasses.replace(base, **d)
        except (TypeError, ValueError) as exc:
            raise self.fail(path, str(exc)) from exc


def model_from_table(cls, d: dict, source: str, path: str, base=None):
    """``base`` (default ``cls()``) with the fields of TOML table ``d`` replaced; unknown or
    invalid fields raise :class:`ScenarioError` naming ``source`` and ``path``."""
    if not isinstance(d, dict):
        raise ScenarioError(f"{source}: {path}: must be a table")
    return Ctx(source).model(cls, d, path, base)


def check_keys(ctx: Ctx, d: Any, allowed: set[str], path: str) -> None:
    """``d`` is a table whose keys are all in ``allowed``."""
    if not isinstance(d, dict):
        raise ctx.fail(path or "(top level)", f"must be a table, got {d!r}")
    for k in d:
        if k not in allowed:
            raise ctx.fail(f"{path}.{k}" if path else k, f"unknown field (known: {', '.join(sorted(allowed))})")


def array_of(ctx: Ctx, d: dict, key: str, path: str = "") -> list:
    """``d[key]``, an array (of tables: each is checked where it is read), or [] if absent."""
    v = d.get(key, [])
    if not isinstance(v, list):
        raise ctx.fail(f"{path}.{key}" if path else key, f"must be an array of tables, got {v!r}")
    return v
