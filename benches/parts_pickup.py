"""Pickup points of detected parts in the robot's base frame, in the simulated cell's
parts station (`earcore.sim.part_station`): a trained detector's activation per part
type, its regions (`locate_parts`: no part counts given), each region's pickup point
back-projected through the camera's pose, against each part's true centre of gravity.

    PYTHONPATH=python python benches/parts_pickup.py --model runs/parts --views 100 --seed 1001

A part counts as found when a region of its type's activation covers most of its
visible pixels; a region covering two or more parts of the type (touching parts) is
counted apart ("merged"): its pickup point lies between them. The camera's pose is
taken through a calibration with the errors measured for `earcore calibrate`
(benches/RESULTS.md, Calibration: at most 1.5 mm and 0.06° per camera with all
frames): each view's pose is moved by that much in a random direction and turned by
that much about a random axis; `--calibration-error 0,0` uses the true pose.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sweep import machine  # noqa: E402


def measure(args: argparse.Namespace) -> dict:
    from earcore.parts.find import detector_beliefs
    from earcore.parts.locate import locate_parts
    from earcore.parts.oneshot_data import MIN_PIXELS
    from earcore.parts.train import load_detector
    from earcore.sim.part_station import PartStation, calibrated_pose

    detector, meta = load_detector(args.model)
    o = detector.options
    rng = np.random.default_rng(args.seed)
    millimetres, degrees = args.calibration_error
    errors, merged, missed, parts, views = [], [], 0, 0, 0
    per_type: dict[str, list[float]] = {}
    started = time.perf_counter()
    with PartStation(width=o.width, height=o.height, seed=args.seed, classes=tuple(meta["classes"])) as station:
        for index in range(args.views):
            view = station.view(index)
            pose = calibrated_pose(view.base_from_camera, millimetres, degrees, rng)
            beliefs = detector_beliefs(detector, view.rgb, view.depth_mm if o.in_channels == 4 else None)
            views += 1
            for cls in np.unique(view.classes):
                regions = locate_parts(beliefs[cls], view.depth_m, view.intrinsics, pose, threshold=0.5, min_pixels=MIN_PIXELS)
                slots = np.flatnonzero(view.classes == cls)
                masks = {int(i): view.instances == i + 1 for i in slots}
                covers = [[int(i) for i, m in masks.items() if m.sum() >= MIN_PIXELS and (region & m).sum() > 0.5 * m.sum()] for _, region in regions]
                for i, m in masks.items():
                    if m.sum() < MIN_PIXELS:
                        continue
                    parts += 1
                    hits = [k for k, c in enumerate(covers) if i in c]
                    if not hits:
                        missed += 1
                        continue
                    pick, _ = regions[hits[0]]
                    error = float(np.linalg.norm(pick.base - view.centres[i]))
                    (merged if len(covers[hits[0]]) > 1 else errors).append(error)
                    if len(covers[hits[0]]) == 1:
                        per_type.setdefault(view.class_names[cls], []).append(error)
    return {
        "views": views,
        "parts": parts,
        "found_alone": len(errors),
        "merged": len(merged),
        "missed": missed,
        "median_mm": 1000 * float(np.median(errors)) if errors else float("nan"),
        "p90_mm": 1000 * float(np.percentile(errors, 90)) if errors else float("nan"),
        "within_1cm": float(np.mean(np.array(errors) < 0.01)) if errors else float("nan"),
        "merged_median_mm": 1000 * float(np.median(merged)) if merged else float("nan"),
        "per_type_median_mm": {k: 1000 * float(np.median(v)) for k, v in sorted(per_type.items())},
        "seconds": time.perf_counter() - started,
    }


def report(r: dict, args: argparse.Namespace) -> str:
    mm, deg = args.calibration_error
    lines = [
        f"Pickup points in the base frame, {date.today().isoformat()}, {machine()}",
        f"detector {args.model}, {r['views']} station views (seed {args.seed}), calibration error {mm:g} mm / {deg:g}°, {r['seconds']:.0f} s",
        "",
        "| Parts | Found alone | Median error | 90th percentile | Within 1 cm | Merged with a touching part (median) | Missed |",
        "|---|---|---|---|---|---|---|",
        f"| {r['parts']} | {r['found_alone']} | {r['median_mm']:.1f} mm | {r['p90_mm']:.1f} mm | {100 * r['within_1cm']:.0f} % "
        f"| {r['merged']} ({r['merged_median_mm']:.1f} mm) | {r['missed']} |",
        "",
        "Median error per type (parts found alone): " + ", ".join(f"{k} {v:.1f} mm" for k, v in r["per_type_median_mm"].items()),
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True, help="a trained parts detector (run folder or checkpoint)")
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1001, help="the station's scenes (use one the detector was not trained on)")
    parser.add_argument(
        "--calibration-error",
        type=lambda t: tuple(float(x) for x in t.split(",")),
        default=(1.5, 0.06),
        metavar="MM,DEG",
        help="the camera pose's error (default 1.5,0.06)",
    )
    parser.add_argument("--out", type=Path, default=Path("benches/out/parts-pickup"))
    args = parser.parse_args()
    if len(args.calibration_error) != 2:
        parser.error("--calibration-error takes MM,DEG")
    result = measure(args)
    text = report(result, args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.md").write_text(text + "\n")
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
