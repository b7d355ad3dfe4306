"""Labelled robot images per second (`earcore dataset robots`) at 128×106 with 1 and 2
worker processes, and the papers' UR set (4,350 images) end to end; prints a markdown
table.

    PYTHONPATH=python python benches/dataset_generation.py            # everything (~3 min on 2 cores)
    PYTHONPATH=python python benches/dataset_generation.py --quick    # 1 % of the set per rate
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from earcore.app.dataset import main as dataset


def run(folder: Path, args: list[str]) -> tuple[int, float]:
    started = time.perf_counter()
    assert dataset(["robots", "--out", str(folder), "--quiet", *args]) == 0
    seconds = time.perf_counter() - started
    manifest = json.loads((folder / "manifest.json").read_text())
    return sum(s["samples"] for s in manifest["shards"]), seconds


def coverage(folder: Path) -> np.ndarray:
    import csv

    values = []
    for path in sorted(folder.glob("shard-*.csv")):
        values += [float(r["coverage"]) for r in csv.DictReader(open(path))]
    return np.array(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sets only (a smoke run)")
    args = parser.parse_args()
    rate_scale = "0.02" if args.quick else "0.1"
    rows = []
    with tempfile.TemporaryDirectory(prefix="earcore-bench-") as tmp:
        for workers in (1, 2):
            n, s = run(Path(tmp) / f"rate{workers}", ["--scale", rate_scale, "--workers", str(workers), "--shard-size", "32"])
            rows.append((f"UR set × {rate_scale}, {workers} worker{'s' if workers > 1 else ''}", n, s))
        if not args.quick:
            folder = Path(tmp) / "papers"
            n, s = run(folder, ["--workers", "2"])
            rows.append(("the papers' UR set (recordings), 2 workers", n, s))
            size = sum(p.stat().st_size for p in folder.iterdir())
            c = coverage(folder)
    print(f"{time.strftime('%Y-%m-%d')}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, 128×106\n")
    print("| run | images | seconds | images/s |")
    print("|---|---:|---:|---:|")
    for name, n, s in rows:
        print(f"| {name} | {n} | {s:.1f} | {n / s:.1f} |")
    if not args.quick:
        edges = [0, 0.03, 0.05, 0.1, 0.15, 0.2, 0.25, 1.0]
        hist, _ = np.histogram(c, edges)
        print(
            f"\nDataset size: {size / 2**20:.1f} MiB. Robot coverage: median {np.median(c):.3f}, "
            f"{np.mean((c >= 0.05) & (c <= 0.2)):.0%} within 5-20 %, {np.mean((c >= 0.03) & (c <= 0.25)):.0%} within 3-25 %"
        )
        print("\n| coverage | " + " | ".join(f"{a:.0%}-{b:.0%}" for a, b in zip(edges[:-1], edges[1:])) + " |")
        print("|---" * (len(edges)) + "|")
        print("| images | " + " | ".join(str(h) for h in hist) + " |")


if __name__ == "__main__":
    main()
