"""Validators of scene keys: one rule per kind of value, used by every scene section.

Each function checks one value read from a scene (TOML) and returns it in
its Python type, or raises :class:`ptrack.errors.UserError` naming the key
(``section.key``), the value and what is expected. :mod:`sim.scene` (the
main sections) and :mod:`sim.interactions` (the pair-force sections) both
import from here, so the two import in one direction only
(``scene -> interactions -> validate``).
"""
from __future__ import annotations

import math

from ptrack.errors import UserError

__all__ = ["where", "number", "integer", "boolean", "choice", "vec3", "section", "missing"]


def where(section: str, key: str) -> str:
    """``section.key`` (or ``key`` at the top level)."""
    return f"{section}.{key}" if section else key


def number(section, key, v, *, positive=False, nonneg=False, lo=None, hi=None) -> float:
    """A finite real number, optionally > 0, >= 0, or in [lo, hi]."""
    name = where(section, key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise UserError(f"scene key {name} = {v!r} is not a number", f"give {name} as a number in SI units")
    v = float(v)
    if not math.isfinite(v):
        raise UserError(f"scene key {name} = {v!r} is not finite", f"give a finite {name}")
    if positive and v <= 0:
        raise UserError(f"scene key {name} = {v!r} must be positive", f"give a positive {name}")
    if nonneg and v < 0:
        raise UserError(f"scene key {name} = {v!r} must be non-negative", f"give {name} >= 0")
    if lo is not None and v < lo or hi is not None and v > hi:
        raise UserError(f"scene key {name} = {v!r} is out of range", f"give {name} in [{lo}, {hi}]")
    return v


def integer(section, key, v, *, positive=False, nonneg=False) -> int:
    """A whole number (not a bool), optionally > 0 or >= 0."""
    name = where(section, key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise UserError(f"scene key {name} = {v!r} is not an integer", f"give {name} as a whole number")
    if positive and v <= 0:
        raise UserError(f"scene key {name} = {v!r} must be positive", f"give a positive {name}")
    if nonneg and v < 0:
        raise UserError(f"scene key {name} = {v!r} must be non-negative", f"give {name} >= 0")
    return int(v)


def boolean(section, key, v) -> bool:
    """true or false."""
    if not isinstance(v, bool):
        raise UserError(f"scene key {where(section, key)} = {v!r} is not true/false",
                        f"give {where(section, key)} = true or false")
    return v


def choice(section, key, v, choices):
    """One of ``choices`` (strings)."""
    if not isinstance(v, str) or v not in choices:
        raise UserError(f"scene key {where(section, key)} = {v!r} is not allowed",
                        f"choose one of: {', '.join(repr(c) for c in choices)}")
    return v


def vec3(section, key, v, *, positive=False) -> tuple:
    """A 3-vector of finite numbers."""
    name = where(section, key)
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise UserError(f"scene key {name} = {v!r} is not a 3-vector", f"give {name} as [x, y, z] in SI units")
    return tuple(number(section, f"{key}[{i}]", c, positive=positive) for i, c in enumerate(v))


def section(raw: dict, name: str, allowed: tuple[str, ...], required: bool = False) -> dict:
    """The table ``raw[name]`` with only ``allowed`` keys ({} when absent and not required)."""
    if name not in raw:
        if required:
            raise UserError(f"scene has no [{name}] section", f"add a [{name}] section")
        return {}
    sec = raw[name]
    if not isinstance(sec, dict):
        raise UserError(f"scene key {name} = {sec!r} is not a section", f"write it as a [{name}] table")
    unknown = [k for k in sec if k not in allowed]
    if unknown:
        raise UserError(f"unknown key {name}.{unknown[0]} in the scene",
                        f"allowed keys in [{name}]: {', '.join(allowed)}")
    return sec


def missing(sec, key):
    """Raise: a required key is absent."""
    raise UserError(f"scene lacks {sec}.{key}", f"give {sec}.{key} (SI units)")
