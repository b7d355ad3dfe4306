"""Timing shared by the side-by-side benchmark scripts."""

from __future__ import annotations

import statistics
import time


def median_time(fn, repeats: int) -> tuple[float, object]:
    """The median wall time (s) of `repeats` calls of `fn` after one warm-up call, and
    the last call's result."""
    fn()
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result
