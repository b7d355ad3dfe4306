"""The metrics log's curves: one panel per metric, bookkeeping left out, PNGs written."""

from __future__ import annotations

import json

import pytest

from earcore.learning.metrics_log import curve_keys, plot_metrics, read_metrics


def test_curves_leave_out_bookkeeping_and_loss_weights():
    rows = [
        {"kind": "eval", "step": 10, "seconds": 3.0, "time": 1.0, "samples": 512, "eval_seconds": 1.2, "joints_median_cm": 9.5, "mask_iou": 0.9},
        {"kind": "train", "step": 10, "seconds": 3.0, "mask": 0.2, "w_mask": 1.0, "lr": 1e-3, "note": "text"},
    ]
    assert curve_keys(rows) == ["joints_median_cm", "lr", "mask", "mask_iou"]


def test_plot_writes_both_pictures_and_a_truncated_line_is_skipped(tmp_path):
    pytest.importorskip("matplotlib")
    path = tmp_path / "metrics.jsonl"
    records = [{"kind": "train", "step": s, "seconds": s / 10, "total": 1.0 / s} for s in range(1, 6)]
    records += [{"kind": "eval", "step": 5, "seconds": 0.5, "joints_median_cm": 12.0}]
    path.write_text("".join(json.dumps(r) + "\n" for r in records) + '{"kind": "tra')
    assert len(read_metrics(path)) == len(records)
    written = plot_metrics(path)
    assert sorted(p.name for p in written) == ["eval.png", "losses.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in written)


def test_comparison_has_a_panel_per_metric_and_names_what_was_logged(tmp_path):
    pytest.importorskip("matplotlib")
    from earcore.learning.metrics_log import plot_comparison
    from earcore.learning.png import read as read_png

    runs = {}
    for name, slope in (("multi", 1.0), ("keypoint", 2.0)):
        path = tmp_path / f"{name}.jsonl"
        rows = [{"kind": "eval", "step": s, "seconds": 60.0 * s, "joints_median_cm": 20 - slope * s, "mask_iou": 0.1 * s} for s in range(1, 5)]
        path.write_text("".join(json.dumps(r) + "\n" for r in rows))
        runs[name] = path
    out = plot_comparison(runs, ["joints_median_cm", "mask_iou"], tmp_path / "curves.png", title="two runs")
    assert out is not None
    image = read_png(out)
    # 3.6 × 3.0 inches per panel at 90 dpi
    assert image.shape[:2] == (270, 648)
    with pytest.raises(ValueError, match="logged: joints_median_cm, mask_iou"):
        plot_comparison(runs, ["base_median_cm"], tmp_path / "none.png")
