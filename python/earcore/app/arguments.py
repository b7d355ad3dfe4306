"""The command line's argument parsing: one parser class whose errors are one line
naming the option, and number types that check their range as they parse."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn

__all__ = ["Parser", "count", "fail", "positive", "positive_int", "scale", "seconds"]


class Parser(argparse.ArgumentParser):
    """`argparse.ArgumentParser` that reports a bad argument in one line (no usage
    block) and exits with status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind: Callable[[str], float], text: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def positive(text: str) -> float:
    """A finite number > 0."""
    value = _number(float, text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def scale(text: str) -> float:
    """A camera resolution factor in [0.05, 4]."""
    value = _number(float, text)
    if not 0.05 <= value <= 4.0:
        raise argparse.ArgumentTypeError(f"must be in [0.05, 4], got {text!r}")
    return value


def seconds(text: str) -> float:
    """A duration in seconds, > 0 and at most a day."""
    value = positive(text)
    if value > 86400:
        raise argparse.ArgumentTypeError(f"must be at most 86400 (a day), got {text!r}")
    return value


def positive_int(text: str) -> int:
    """A whole number >= 1."""
    return count(text, 1)


def count(text: str, minimum: int = 0) -> int:
    """A whole number >= `minimum` (0 by default) and below 2^31."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not minimum <= value < 2**31:
        raise argparse.ArgumentTypeError(f"must be in [{minimum}, 2^31), got {text!r}")
    return value


def fail(prog: str, message: str, status: int = 2) -> int:
    """Print `prog: error: message` on stderr and return `status` (for `return fail(...)`)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return status
