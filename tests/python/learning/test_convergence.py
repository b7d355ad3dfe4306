"""The Fig. 12 convergence point on curves whose answer is known, and the two-sample
KS test against SciPy's and against values counted by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from earcore.learning.convergence import convergence_point
from earcore.learning.significance import ks_2samp


def test_a_drop_onto_a_noisy_plateau_converges_on_the_plateau_soon_after_it_starts():
    """Never inside the drop; on the plateau a point lies inside ±σ/2 with probability
    0.38, so the first one inside comes a geometric number of points after its start."""
    rng = np.random.default_rng(0)
    found = []
    for _ in range(50):
        drop = [5.0, 4.0, 3.0, 2.0, 1.5, 1.2]
        plateau = 1.0 + rng.normal(0.0, 0.01, 40)
        c = convergence_point(np.arange(46) * 500, np.concatenate([drop, plateau]))
        assert c.index >= 6
        assert c.step == 500 * c.index
        assert c.error == pytest.approx(plateau[c.index - 6 :].mean())
        found.append(c.index - 6)
    assert np.median(found) <= 2 and max(found) <= 12


def test_hand_worked_example():
    # round 1: mean 3.5, std 2.9155, window [2.04, 4.96]: 10 and 5 out, 3 in → start at index 2
    # round 2: mean 1.75, std 0.829, window [1.335, 2.165]: 3 out, 2 in → start at index 3
    # round 3: [2, 1, 1.5, 2, 1.5]: mean 1.6, std 0.374, window [1.413, 1.787]: 2 out, 1 out, 1.5 in → index 5
    # round 4: [1.5, 2, 1.5]: mean 1.667, std 0.236, window [1.549, 1.785]: 1.5 out, 2 out → kept min_points=3 at index 5
    c = convergence_point([0, 1, 2, 3, 4, 5, 6, 7], [10.0, 5.0, 3.0, 2.0, 1.0, 1.5, 2.0, 1.5])
    assert c.index == 5 and c.error == pytest.approx(5.0 / 3.0) and c.rounds == 3


def test_exponential_curves_converge_where_the_decay_drops_into_the_noise():
    """a·e^(-t/τ) + c + N(0, s): the window's half-width is about s/2 once the decay is
    gone, so a point is accepted when the decay term is about the noise, t* = τ ln(a/s):
    the median detection within 2 evaluation intervals of t*, every one between where
    the decay is 3 s and where it is s/10."""
    rng = np.random.default_rng(1)
    a, tau, c0, s = 1.0, 4000.0, 0.2, 0.01
    steps = np.arange(0, 60_000, 500, dtype=float)
    expected = tau * math.log(a / s)
    found = []
    for _ in range(40):
        curve = a * np.exp(-steps / tau) + c0 + rng.normal(0.0, s, steps.size)
        found.append(convergence_point(steps, curve).step)
    found_arr = np.array(found)
    assert abs(np.median(found_arr) - expected) <= 2 * 500
    assert found_arr.min() >= tau * math.log(a / (3 * s)) and found_arr.max() <= tau * math.log(10 * a / s)


def test_a_flat_curve_has_converged_at_once_and_bad_curves_are_refused():
    assert convergence_point([1, 2, 3, 4], [1.0, 1.0, 1.0, 1.0]).index == 0
    with pytest.raises(ValueError, match="finite"):
        convergence_point([1, 2, 3], [1.0, float("nan"), 1.0])
    with pytest.raises(ValueError, match="increase"):
        convergence_point([1, 1, 3], [1.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="empty"):
        convergence_point([], [])


def test_ks_statistic_and_pvalue_match_scipy_exact_and_the_limit_distribution():
    rng = np.random.default_rng(2)
    for n, m, shift in [(8, 8, 0.0), (8, 8, 1.5), (5, 9, 0.7), (20, 12, 0.3), (60, 70, 0.2), (150, 120, 0.4)]:
        a, b = rng.normal(0, 1, n), rng.normal(shift, 1, m)
        ours = ks_2samp(a, b)
        ref = scipy.stats.ks_2samp(a, b, method="exact")
        assert ours.statistic == pytest.approx(ref.statistic, abs=1e-12)
        if n * m <= 10_000:
            assert ours.pvalue == pytest.approx(ref.pvalue, rel=1e-6, abs=1e-12)
        else:  # Kolmogorov's limit at sqrt(nm/(n+m))·D
            limit = scipy.stats.kstwobign.sf(math.sqrt(n * m / (n + m)) * ref.statistic)
            assert ours.pvalue == pytest.approx(limit, rel=1e-9)


def test_ks_large_and_lopsided_samples():
    # perfectly interleaved large samples: D tiny, p = 1 (the limit series, summed naively, says 0.04)
    a = np.arange(0, 400_000, 2, dtype=float)
    r = ks_2samp(a, a + 1.0)
    assert r.pvalue == pytest.approx(1.0) and not r.different()
    # a small sample against a large one is counted exactly, as SciPy's exact test does
    rng = np.random.default_rng(5)
    small, large = rng.normal(0.5, 1, 3), rng.normal(0, 1, 5000)
    assert ks_2samp(small, large).pvalue == pytest.approx(scipy.stats.ks_2samp(small, large, method="exact").pvalue, rel=1e-6)


def test_ks_counted_by_hand():
    # a = {1, 2}, b = {3, 4}: D = 1; of the C(4, 2) = 6 orderings only two ({a, a, b, b}
    # and {b, b, a, a}) reach D = 1, so p = 2/6.
    r = ks_2samp([1.0, 2.0], [3.0, 4.0])
    assert r.statistic == 1.0 and r.pvalue == pytest.approx(1.0 / 3.0)
    # identical samples: D = 0, p = 1
    same = ks_2samp([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    assert same.statistic == 0.0 and same.pvalue == 1.0 and not same.different()
    assert ks_2samp(np.arange(8.0), np.arange(8.0) + 100).different()
    with pytest.raises(ValueError, match="empty"):
        ks_2samp([], [1.0])
