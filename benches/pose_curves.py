"""Accuracy against training time of several pose runs on shared axes (the runs'
evaluations on the test split during training):

    PYTHONPATH=python python benches/pose_curves.py --out benches/figures/pose-curves.png \\
        multi=benches/out/pose/multi cascade=benches/out/pose/cascade keypoint=benches/out/pose/keypoint
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from earcore.learning.metrics_log import plot_comparison

KEYS = ["joints_median_cm", "base_median_cm", "mask_iou", "type_accuracy"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="LABEL=FOLDER", help="a run folder (with metrics.jsonl) and its label")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--keys", default=",".join(KEYS), help="comma-separated evaluation metrics, one panel each")
    parser.add_argument("--title", default="")
    args = parser.parse_args()
    runs = {}
    for item in args.runs:
        label, sep, folder = item.partition("=")
        if not sep or not label:
            parser.error(f"a run is LABEL=FOLDER, got {item!r}")
        path = Path(folder) / "metrics.jsonl"
        if not path.is_file():
            parser.error(f"{path} does not exist")
        runs[label] = path
    try:
        written = plot_comparison(runs, args.keys.split(","), args.out, title=args.title)
    except ValueError as exc:
        parser.error(str(exc))
    if written is None:
        print("matplotlib is not installed: no picture", file=sys.stderr)
        return 1
    print(written)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
