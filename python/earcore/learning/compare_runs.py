"""Comparing training methods over many runs, the IROS 2018 paper's way: each run's
convergence point (Fig. 12, `earcore.learning.convergence`) and its error after
convergence, per method; the two-sample KS test between a reference method and every
other one on both (α = 0.05); the relative improvement of the reference (Table II's
layout); and Fig. 13's double box plot of convergence iteration against error.

    runs = {"auxnet": [folder, ...], "kgc": [...], ...}
    comparison = compare_methods({m: [eval_curve(f, "joints_mean_cm") for f in fs] for m, fs in runs.items()})
    print(comparison.markdown("auxnet"))
    plot_convergence_boxes(comparison, "fig13.png")
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from earcore.learning.convergence import Convergence, convergence_point
from earcore.learning.metrics_log import pyplot, read_metrics
from earcore.learning.significance import KSResult, ks_2samp

__all__ = ["Comparison", "MethodRuns", "compare_methods", "eval_curve", "plot_convergence_boxes"]

Curve = tuple[np.ndarray, np.ndarray]


def eval_curve(folder: str | Path, metric: str) -> Curve:
    """(steps, values) of `metric` over a run's evaluations (its metrics.jsonl)."""
    path = Path(folder) / "metrics.jsonl" if Path(folder).is_dir() else Path(folder)
    rows = [r for r in read_metrics(path) if r.get("kind") == "eval" and isinstance(r.get(metric), (int, float))]
    if not rows:
        raise ValueError(f"{path} has no evaluation with {metric!r}")
    by_step = {int(r["step"]): float(r[metric]) for r in rows}  # a resumed run's repeated step: the last
    steps = np.array(sorted(by_step), dtype=np.float64)
    return steps, np.array([by_step[int(s)] for s in steps])


@dataclass
class MethodRuns:
    name: str
    points: list[Convergence] = field(default_factory=list)

    @property
    def iterations(self) -> np.ndarray:
        return np.array([p.step for p in self.points])

    @property
    def errors(self) -> np.ndarray:
        return np.array([p.error for p in self.points])


@dataclass
class Comparison:
    methods: dict[str, MethodRuns]
    metric: str = "error"

    def tests(self, reference: str) -> dict[str, tuple[KSResult, KSResult]]:
        """KS tests of `reference` against every other method: (iterations, errors)."""
        ref = self.methods[reference]
        return {name: (ks_2samp(ref.iterations, m.iterations), ks_2samp(ref.errors, m.errors)) for name, m in self.methods.items() if name != reference}

    def markdown(self, reference: str | None = None, alpha: float = 0.05) -> str:
        lines = [
            f"| Method | Runs | Convergence iteration, median (mean) | {self.metric} after convergence, median (mean) |",
            "|---|---|---|---|",
        ]
        for name, m in self.methods.items():
            it, er = m.iterations, m.errors
            lines.append(f"| {name} | {len(m.points)} | {np.median(it):.0f} ({it.mean():.0f}) | {np.median(er):.4g} ({er.mean():.4g}) |")
        if reference is None or reference not in self.methods:
            return "\n".join(lines) + "\n"
        ref = self.methods[reference]
        lines += [
            "",
            f"{reference} against each method (means over runs; negative: {reference} lower). "
            f"KS: two-sample Kolmogorov-Smirnov p-value, * where the distributions differ at α = {alpha}.",
            "",
            f"| {reference} vs. | Convergence iteration | KS p (iterations) | {self.metric} | KS p ({self.metric}) |",
            "|---|---|---|---|---|",
        ]
        for name, (t_it, t_er) in self.tests(reference).items():
            other = self.methods[name]
            d_it = 100.0 * (ref.iterations.mean() / max(other.iterations.mean(), 1e-12) - 1.0)
            d_er = 100.0 * (ref.errors.mean() / max(other.errors.mean(), 1e-12) - 1.0)
            mark_it = "*" if t_it.different(alpha) else ""
            mark_er = "*" if t_er.different(alpha) else ""
            lines.append(f"| {name} | {d_it:+.1f} % | {t_it.pvalue:.3f}{mark_it} | {d_er:+.1f} % | {t_er.pvalue:.3f}{mark_er} |")
        return "\n".join(lines) + "\n"


def compare_methods(curves: Mapping[str, Sequence[Curve]], *, metric: str = "error", width: float = 0.5, min_points: int = 3) -> Comparison:
    """Each run's convergence point and error after convergence, per method."""
    methods: dict[str, MethodRuns] = {}
    for name, runs in curves.items():
        if not runs:
            raise ValueError(f"method {name!r} has no runs")
        methods[name] = MethodRuns(name, [convergence_point(s, e, width=width, min_points=min_points) for s, e in runs])
    return Comparison(methods, metric)


def _box(ax: Any, values: np.ndarray, position: float, horizontal: bool, width: float, colour: str) -> None:
    style = {"color": colour}
    common = {"positions": [position], "widths": width, "manage_ticks": False, "boxprops": style, "whiskerprops": style, "capprops": style, "medianprops": style}
    try:  # matplotlib >= 3.10
        ax.boxplot(values, orientation="horizontal" if horizontal else "vertical", **common, flierprops={"markeredgecolor": colour})
    except TypeError:
        ax.boxplot(values, vert=not horizontal, **common, flierprops={"markeredgecolor": colour})


def plot_convergence_boxes(comparison: Comparison, out: str | Path, *, title: str = "") -> Path | None:
    """Fig. 13's layout: per method a horizontal box of convergence iterations at the
    median error and a vertical box of errors at the median iteration (None without
    matplotlib)."""
    plt = pyplot()
    if plt is None:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (name, m) in enumerate(comparison.methods.items()):
        colour = colours[k % len(colours)]
        it, er = m.iterations, m.errors
        x0, y0 = float(np.median(it)), float(np.median(er))
        spread_x = max(float(np.ptp(it)), 1.0)
        spread_y = max(float(np.ptp(er)), 1e-9)
        _box(ax, it, y0, True, 0.04 * spread_y + 0.02 * y0, colour)
        _box(ax, er, x0, False, 0.04 * spread_x + 0.02 * x0, colour)
        ax.plot([x0], [y0], "o", color=colour, label=f"{name} ({len(m.points)} runs)")
    ax.set_xlabel("convergence iteration (Fig. 12's algorithm)")
    ax.set_ylabel(f"{comparison.metric} after convergence")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
