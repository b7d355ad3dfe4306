"""The many-runs comparison: curves read back from metrics files, convergence points
per method, KS tests that tell a faster method from a slower one (and not two draws of
the same one), Table II's relative figures and Fig. 13's plot file."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.learning.compare_runs import compare_methods, eval_curve, plot_convergence_boxes
from earcore.learning.metrics_log import MetricsLog


def curves(tau: float, level: float, seeds: range) -> list[tuple[np.ndarray, np.ndarray]]:
    steps = np.arange(0, 20_000, 250, dtype=float)
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        out.append((steps, 1.0 * np.exp(-steps / tau) + level + rng.normal(0, 0.005, steps.size)))
    return out


def test_a_faster_method_is_told_apart_and_a_copy_is_not(tmp_path):
    comparison = compare_methods(
        {"fast": curves(800.0, 0.20, range(8)), "slow": curves(2500.0, 0.30, range(8, 16)), "fast-again": curves(800.0, 0.20, range(16, 24))}, metric="joint error"
    )
    fast, slow = comparison.methods["fast"], comparison.methods["slow"]
    assert np.median(fast.iterations) < 0.5 * np.median(slow.iterations)
    assert fast.errors.mean() == pytest.approx(0.20, abs=0.01) and slow.errors.mean() == pytest.approx(0.30, abs=0.01)
    tests = comparison.tests("fast")
    assert tests["slow"][0].different() and tests["slow"][1].different()
    assert not tests["fast-again"][1].different()
    table = comparison.markdown("fast")
    assert "| slow | 8 |" in table and "fast vs." in table and "*" in table
    # Table II's layout: the reference's mean iteration relative to the other's
    row = next(line for line in table.splitlines() if line.startswith("| slow |") and "%" in line)
    expected = 100.0 * (fast.iterations.mean() / slow.iterations.mean() - 1.0)
    assert f"{expected:+.1f} %" in row
    path = plot_convergence_boxes(comparison, tmp_path / "fig13.png", title="test")
    assert path is not None and path.stat().st_size > 5000


def test_curves_come_back_from_a_metrics_file(tmp_path):
    log = MetricsLog(tmp_path / "metrics.jsonl")
    for step, value in [(10, 3.0), (20, 2.0), (20, 1.5), (30, 1.0)]:
        log.write("eval", step, float(step), {"joints_mean_cm": value})
        log.write("train", step, float(step), {"joints": value})
    steps, values = eval_curve(tmp_path, "joints_mean_cm")
    assert steps.tolist() == [10, 20, 30] and values.tolist() == [3.0, 1.5, 1.0]
    with pytest.raises(ValueError, match="no evaluation"):
        eval_curve(tmp_path, "mask_iou")
    with pytest.raises(ValueError, match="no runs"):
        compare_methods({"empty": []})
