"""The charging station's vision on the simulated cell (`charging.locate`): the port
found in both images (narrowed to dark regions and over the full image), the time per
image pair, the reference points' pixel error, and the port's pose against the
simulation's truth by the paper's route (pins triangulated, plane fit and layout) and
by the model fitted to both images at once.

    PYTHONPATH=python python benches/charging_vision.py --parkings 20 --out benches/out/charging-vision

Each parking is rendered once (both cameras, seeded) and matched with each mode; the
report (report.md, results.json) gives medians, 90th percentiles and the worst case.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parkings", type=int, default=20)
    parser.add_argument("--port", default="type2", help="the car's connector: type2 or type1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--camera-scale", type=float, default=1.0)
    parser.add_argument("--repeats", type=int, default=3, help="timings: the best of this many runs per image pair")
    parser.add_argument("--distance", type=float, default=None, help="put the stereo pair this far from the nominal port (m; default: the cell's, about 2.0)")
    parser.add_argument("--angles", default="0,45", help="MIN,MAX: the port's angle to the cameras (degrees, default 0,45)")
    parser.add_argument("--modes", default="narrowed,full", help="which searches to run: narrowed, full or both (default)")
    parser.add_argument("--out", type=Path, default=Path("benches/out/charging-vision"))
    args = parser.parse_args(argv)

    from earcore.charging.connectors import connector
    from earcore.charging.locate import locate
    from earcore.charging.matching import ShapeModel, project_points
    from earcore.sim.charging_cell import ChargingCell, ChargingCellConfig
    from earcore.transforms import mean_pose, rotation_angle

    low, high = (float(v) for v in args.angles.split(","))
    config = ChargingCellConfig(seed=args.seed, port=args.port, camera_scale=args.camera_scale, min_angle_deg=low, max_angle_deg=high)
    if args.distance is not None:
        nominal = np.asarray(config.port_nominal)
        away = np.asarray(config.rig_position) - nominal
        config = replace(config, rig_position=tuple(nominal + away / np.linalg.norm(away) * args.distance))
    modes = [m for m in ("narrowed", "full") if m in args.modes.split(",")]
    rig_at = np.round(config.rig_position, 3).tolist()
    sys_info = f"{args.parkings} parkings, port {args.port}, angles {low:g}-{high:g}°, seed {args.seed}, camera scale {args.camera_scale}, rig {rig_at}"
    cell = ChargingCell(config)
    k = connector(args.port)
    model = ShapeModel.port(k)
    rig = cell.rig
    rows = []
    for i in range(args.parkings):
        parking = cell.park() if i else cell.parking  # the cell's own seeded sequence
        left, right = cell.capture()
        truth = np.linalg.inv(cell.cameras[0].base_from_camera) @ parking.base_from_port
        row: dict = {"angle_deg": parking.angle_deg, "distance_m": float(np.linalg.norm(truth[:3, 3]))}
        estimate = None
        for mode in modes:
            narrow = mode == "narrowed"
            best = np.inf
            for _ in range(args.repeats):
                start = time.perf_counter()
                found = locate(left, right, model, rig, narrow=narrow)
                best = min(best, time.perf_counter() - start)
                estimate = found if narrow or estimate is None else estimate
            row[f"{mode}_ms"] = 1000 * best
            row[f"{mode}_found"] = found is not None
        if estimate is None:
            rows.append(row)
            continue
        errors = []
        for match, (K, dist, from_left) in zip(estimate.matches, ((rig.K_left, rig.dist_left, np.eye(4)), (rig.K_right, rig.dist_right, rig.right_from_left))):
            pose = from_left @ truth
            expected = project_points(k.reference_points @ pose[:3, :3].T + pose[:3, 3], K, dist)
            errors.append(float(np.abs(match.reference_pixels - expected).max()))
        row.update(reference_px=max(errors), scores=[m.score for m in estimate.matches], fit_mm=estimate.fit_mm, flagged=estimate.flagged)
        fused = mean_pose(np.array([estimate.paper, estimate.camera_from_port]))
        for name, pose in (("plane", estimate.paper), ("both", estimate.camera_from_port), ("fused", fused)):
            relative = pose[:3, :3].T @ truth[:3, :3]
            row[f"{name}_mm"] = 1000 * float(np.linalg.norm(pose[:3, 3] - truth[:3, 3]))
            row[f"{name}_deg"] = float(np.degrees(rotation_angle(pose[:3, :3], truth[:3, :3])))
            row[f"{name}_turn_deg"] = float(abs(np.degrees(np.arctan2(relative[1, 0], relative[0, 0]))))
        rows.append(row)
        print(json.dumps({key: (round(v, 3) if isinstance(v, float) else v) for key, v in row.items()}), flush=True)
    cell.close()

    def stat(key: str) -> str:
        values = np.array([r[key] for r in rows if key in r], dtype=float)
        if not len(values):
            return "–"
        return f"{np.median(values):.2f} / {np.percentile(values, 90):.2f} / {values.max():.2f}"

    found = {mode: sum(r.get(f"{mode}_found", False) for r in rows) for mode in ("narrowed", "full")}
    lines = [
        f"# Charging station vision ({sys_info})",
        "",
        "| Quantity | median / p90 / worst |",
        "|---|---|",
        f"| matching, narrowed, per image pair (ms) | {stat('narrowed_ms')} |",
        f"| matching, full image, per image pair (ms) | {stat('full_ms')} |",
        f"| reference points, pixel error (worst of the pair) | {stat('reference_px')} |",
        f"| pose, paper (pins, plane, layout): position (mm) | {stat('plane_mm')} |",
        f"| pose, paper: rotation (°) | {stat('plane_deg')} |",
        f"| pose, paper: turn about the axis (°) | {stat('plane_turn_deg')} |",
        f"| pose, both images: position (mm) | {stat('both_mm')} |",
        f"| pose, both images: rotation (°) | {stat('both_deg')} |",
        f"| pose, both images: turn about the axis (°) | {stat('both_turn_deg')} |",
        f"| pose, mean of the two: position (mm) | {stat('fused_mm')} |",
        f"| pose, mean of the two: rotation (°) | {stat('fused_deg')} |",
        f"| distance to the left camera (m) | {stat('distance_m')} |",
        "",
        f"Found in both images: narrowed {found['narrowed']}/{len(rows)}, full image {found['full']}/{len(rows)}; "
        f"flagged: {sum(bool(r.get('flagged')) for r in rows)}.",
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.md").write_text("\n".join(lines) + "\n")
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
