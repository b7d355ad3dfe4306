"""The two-sample Kolmogorov-Smirnov test (the IROS 2018 paper's significance test, α = 0.05).

D is the largest distance between the two samples' empirical distribution functions.
The two-sided p-value P(D ≥ d | both samples from one continuous distribution) is
exact for n·m ≤ 10,000 and for a sample of at most 10 against one of up to 100,000
(counting the lattice paths from (0, 0) to (n, m) that stay within |i/n - j/m| < d,
in integers, over all C(n+m, n) paths), otherwise from Kolmogorov's limit
distribution at λ = sqrt(nm/(n+m))·d (1 below λ = 0.2, where it is 1 to 1e-9 and
its series converges slowly). Ties are allowed in the data
(D is computed over the pooled values); the p-value then is the continuous case's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["KSResult", "ks_2samp"]

#: n·m up to this: the exact p-value
EXACT_LIMIT = 10_000


@dataclass(frozen=True)
class KSResult:
    statistic: float
    pvalue: float
    n: int
    m: int

    def different(self, alpha: float = 0.05) -> bool:
        """Whether the samples' distributions differ at level `alpha` (H0 rejected)."""
        return self.pvalue < alpha


def _sample(values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    a = np.sort(np.asarray(values, dtype=np.float64).reshape(-1))
    if a.size < 1:
        raise ValueError(f"sample {name} is empty")
    if not np.isfinite(a).all():
        raise ValueError(f"sample {name} holds a value that is not finite")
    return a


def _exact_pvalue(n: int, m: int, dnm: int) -> float:
    """1 - (paths with |i·m - j·n| < dnm at every lattice point) / C(n+m, n)."""
    row = [1 if abs(j * n) < dnm else 0 for j in range(m + 1)]
    for j in range(1, m + 1):
        if row[j]:
            row[j] = row[j - 1]
    for i in range(1, n + 1):
        new = [0] * (m + 1)
        for j in range(m + 1):
            if abs(i * m - j * n) < dnm:
                new[j] = row[j] + (new[j - 1] if j > 0 else 0)
        row = new
    inside = row[m]
    total = math.comb(n + m, n)
    return float(max(0.0, min(1.0, (total - inside) / total)))


def _limit_pvalue(d: float, n: int, m: int) -> float:
    lam = math.sqrt(n * m / (n + m)) * d
    if lam < 0.2:
        return 1.0
    p = 2.0 * sum((-1) ** (k - 1) * math.exp(-2.0 * k * k * lam * lam) for k in range(1, 101))
    return float(max(0.0, min(1.0, p)))


def ks_2samp(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> KSResult:
    """The two-sided two-sample KS test of `a` against `b`."""
    x, y = _sample(a, "a"), _sample(b, "b")
    n, m = x.size, y.size
    pooled = np.concatenate([x, y])
    fx = np.searchsorted(x, pooled, side="right")
    fy = np.searchsorted(y, pooled, side="right")
    dnm = int(np.max(np.abs(fx * m - fy * n)))  # D·n·m, an integer
    d = dnm / (n * m)
    if dnm == 0:
        return KSResult(0.0, 1.0, n, m)
    exact = n * m <= EXACT_LIMIT or (min(n, m) <= 10 and max(n, m) <= 100_000)
    p = _exact_pvalue(n, m, dnm) if exact else _limit_pvalue(d, n, m)
    return KSResult(statistic=float(d), pvalue=p, n=n, m=m)
