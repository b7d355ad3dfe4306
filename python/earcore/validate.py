"""Checks of user settings, each naming the setting (`where`) and what it must be.
The areas' configurations validate themselves with these; the command line reports
a failed check as one line."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from earcore.errors import ConfigError

__all__ = ["ConfigError", "count", "finite", "fraction", "non_negative", "one_of", "positive", "vector"]


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where} must be a number, got {value!r}")
    try:
        return float(value)
    except OverflowError:
        raise ConfigError(f"{where} is too large: {str(value)[:12]}... ({len(str(value))} digits)") from None


def finite(value: Any, where: str) -> float:
    v = _number(value, where)
    if not math.isfinite(v):
        raise ConfigError(f"{where} must be finite, got {value!r}")
    return v


def positive(value: Any, where: str, *, at_most: float | None = None) -> float:
    """A finite number > 0 (and ≤ `at_most` if given)."""
    v = finite(value, where)
    if v <= 0:
        raise ConfigError(f"{where} must be > 0, got {value!r}")
    if at_most is not None and v > at_most:
        raise ConfigError(f"{where} must be at most {at_most:g}, got {value!r}")
    return v


def non_negative(value: Any, where: str) -> float:
    v = finite(value, where)
    if v < 0:
        raise ConfigError(f"{where} must be >= 0, got {value!r}")
    return v


def fraction(value: Any, where: str, *, zero: bool = True) -> float:
    """A number in [0, 1] ((0, 1] with `zero=False`)."""
    v = finite(value, where)
    if not (0 <= v <= 1) or (not zero and v == 0):
        raise ConfigError(f"{where} must be in {'[0' if zero else '(0'}, 1], got {value!r}")
    return v


def count(value: Any, where: str, *, minimum: int = 1) -> int:
    """A whole number >= `minimum`."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where} must be a whole number, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{where} must be >= {minimum}, got {value!r}")
    return value


def one_of(value: Any, options: Iterable[Any], where: str) -> Any:
    options = list(options)
    if value not in options:
        raise ConfigError(f"{where} must be one of {', '.join(repr(o) for o in options)}, got {value!r}")
    return value


def vector(value: Any, where: str, length: int | None = None) -> list[float]:
    """A list of finite numbers (of `length` entries if given)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise ConfigError(f"{where} must be a list of numbers, got {value!r}")
    items = list(value)
    if length is not None and len(items) != length:
        raise ConfigError(f"{where} must have {length} entries, got {len(items)}")
    return [finite(v, f"{where}[{i}]") for i, v in enumerate(items)]
