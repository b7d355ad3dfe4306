"""Training metrics as JSON lines (one object per record: `kind` "train" or "eval",
`step`, `seconds` of training, `wall` time since the run began, then the values) and
their curves as PNG (matplotlib, imported only when plotting)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["MetricsLog", "plot_comparison", "plot_metrics", "pyplot", "read_metrics"]


def _plain(value: Any) -> Any:
    if hasattr(value, "item") and getattr(value, "ndim", 0) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # JSON has no NaN/inf; keep them readable
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


class MetricsLog:
    """Appends records to `path` (`metrics.jsonl`); a resumed run appends to the same file
    after dropping what came after its checkpoint (`keep_until`)."""

    def __init__(self, path: str | Path, *, enabled: bool = True):
        self.path = Path(path)
        self.enabled = enabled
        if enabled:
            self.path.parent.mkdir(parents=True, exist_ok=True)

    def keep_until(self, step: int) -> int:
        """Drop the records after `step` (those of steps a crashed run did after its last
        checkpoint, which the resumed run does again; a truncated last line too); returns
        how many were dropped. The file is rewritten atomically."""
        if not self.enabled or not self.path.is_file():
            return 0
        lines = self.path.read_text().splitlines()
        kept = []
        for line in lines:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(record, dict) and int(record.get("step", 0)) <= step:
                kept.append(line)
        if len(kept) != len(lines):
            tmp = self.path.with_name(f".{self.path.name}.tmp")
            tmp.write_text("".join(line + "\n" for line in kept))
            tmp.replace(self.path)
        return len(lines) - len(kept)

    def write(self, kind: str, step: int, seconds: float, values: Mapping[str, Any]) -> None:
        if not self.enabled:
            return
        record = {"kind": kind, "step": int(step), "seconds": round(float(seconds), 3), "time": round(time.time(), 3), **_plain(dict(values))}
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Every record of a metrics file (a truncated last line, from a killed run, is skipped)."""
    out = []
    for line in Path(path).read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


#: Fields of a record that are not curves (loss weights, "w_*", are left out too).
BOOKKEEPING = ("kind", "step", "seconds", "time", "samples", "eval_seconds")


def curve_keys(rows: list[dict]) -> list[str]:
    """The numeric fields of `rows` worth a curve, sorted."""
    return sorted({k for r in rows for k, v in r.items() if k not in BOOKKEEPING and not k.startswith("w_") and isinstance(v, (int, float))})


def pyplot() -> Any:
    """matplotlib's pyplot without a display; None if matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plot_comparison(runs: Mapping[str, str | Path], keys: list[str], out: str | Path, *, title: str = "") -> Path | None:
    """Several runs' evaluation curves on shared axes: one panel per metric in `keys`,
    one line per run (`runs`: label → metrics file), against training minutes. Returns
    the PNG written; None if matplotlib is not installed. A metric no run logged is a
    `ValueError` naming those that were logged."""
    plt = pyplot()
    if plt is None:
        return None
    rows = {label: [r for r in read_metrics(path) if r.get("kind") == "eval"] for label, path in runs.items()}
    logged = sorted({k for rs in rows.values() for k in curve_keys(rs)})
    missing = [k for k in keys if k not in logged]
    if missing:
        raise ValueError(f"no run logged {', '.join(missing)}; logged: {', '.join(logged) or 'nothing'}")
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.0), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for index, (label, rs) in enumerate(rows.items()):
            pts = [(r["seconds"] / 60.0, r[key]) for r in rs if isinstance(r.get(key), (int, float))]
            if pts:  # a run keeps its colour in every panel, whichever metrics it lacks
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=".", lw=1, label=label, color=f"C{index % 10}")
        ax.set_xlabel("training minutes")
        ax.set_title(key, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(target, dpi=90)
    plt.close(fig)
    return target


def plot_metrics(path: str | Path, out: str | Path | None = None) -> list[Path]:
    """Curves of a metrics file: `losses.png` (training losses against step) and
    `eval.png` (each evaluation metric against training minutes: the accuracy-vs-time
    curve). Returns the files written; none if matplotlib is not installed."""
    plt = pyplot()
    if plt is None:
        return []
    path = Path(path)
    if not path.is_file():
        return []
    folder = Path(out) if out is not None else path.parent
    folder.mkdir(parents=True, exist_ok=True)
    records = read_metrics(path)
    written = []
    for kind, x_key, name in (("train", "step", "losses.png"), ("eval", "seconds", "eval.png")):
        rows = [r for r in records if r.get("kind") == kind]
        keys = curve_keys(rows)
        if not rows or not keys:
            continue
        fig, axes = plt.subplots(len(keys), 1, figsize=(7, 1.8 * len(keys)), sharex=True, squeeze=False)
        for ax, key in zip(axes[:, 0], keys):
            pts = [(r[x_key], r[key]) for r in rows if isinstance(r.get(key), (int, float))]
            xs = [p[0] / 60.0 if x_key == "seconds" else p[0] for p in pts]
            ax.plot(xs, [p[1] for p in pts], lw=1)
            ax.set_ylabel(key, fontsize=8)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("training minutes" if x_key == "seconds" else "step")
        fig.tight_layout()
        target = folder / name
        fig.savefig(target, dpi=90)
        plt.close(fig)
        written.append(target)
    return written
