"""When did a training run converge? The IROS 2018 paper's algorithm (its Fig. 12).

A validation curve is assumed to fall and then scatter (normally) around its final
level. Take the mean μ and standard deviation σ of the curve, accept the window
μ ± `width`·σ (the paper: ±σ/2), drop the earliest points up to the first one inside
the window, recompute μ and σ on what is left, and repeat until the first point left
lies inside its window. That point is the **convergence point**; the mean of the
points from it on is the **error after convergence**.

The paper leaves open whether "the earliest points outside the window" are the
leading run of points outside (chosen here: a noisy plateau has points outside ±σ/2
everywhere, so dropping every outside point would leave nothing) or all of them.
At least `min_points` points are kept, so a curve that never settles converges at
its last `min_points` points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Convergence", "convergence_point"]


@dataclass(frozen=True)
class Convergence:
    #: the step (iteration) of the convergence point
    step: float
    #: its index in the curve
    index: int
    #: the mean error from the convergence point on
    error: float
    #: the standard deviation from the convergence point on
    spread: float
    #: how many window updates it took
    rounds: int


def convergence_point(steps: Sequence[float] | np.ndarray, errors: Sequence[float] | np.ndarray, *, width: float = 0.5, min_points: int = 3) -> Convergence:
    """The convergence point of the curve `errors` evaluated at `steps` (increasing)."""
    s = np.asarray(steps, dtype=np.float64).reshape(-1)
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if s.shape != e.shape:
        raise ValueError(f"steps and errors differ in length: {s.size} and {e.size}")
    if s.size < 1:
        raise ValueError("an empty curve has no convergence point")
    if not (np.isfinite(s).all() and np.isfinite(e).all()):
        raise ValueError("steps and errors must be finite (a diverged run has no convergence point)")
    if s.size > 1 and not (np.diff(s) > 0).all():
        raise ValueError("steps must increase")
    if not (np.isfinite(width) and width > 0):
        raise ValueError(f"width must be > 0, got {width!r}")
    if min_points < 1:
        raise ValueError(f"min_points must be >= 1, got {min_points!r}")
    start, rounds = 0, 0
    last = max(0, e.size - min_points)
    while start < last:
        rest = e[start:]
        mu, sigma = float(rest.mean()), float(rest.std())
        inside = np.abs(rest - mu) <= width * sigma
        first = int(np.argmax(inside)) if inside.any() else rest.size
        if first == 0:
            break
        start = min(start + first, last)
        rounds += 1
    rest = e[start:]
    return Convergence(step=float(s[start]), index=start, error=float(rest.mean()), spread=float(rest.std()), rounds=rounds)
