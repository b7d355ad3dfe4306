"""Pre-processing of one 512×424 depth frame (crop, voxel grid, outlier removal),
earcore and open3d-cpu on the same points in one run.

The frame is camera 0 of the perception benchmark's first recorded frame set (a Kinect
V2-like camera in the simulated cell, back-projected through its lens), in the robot's
base frame. Stages, in Paper II's order: keep the points within 1.5 m of the base, a
2 cm voxel grid, statistical outlier removal (k = 20, 2σ). open3d does the same with
its own voxel grid and the crop in numpy (it has no sphere crop). Its grid is anchored at
the cloud's lower corner instead of the origin: the table top lies at z = 0, on one of
earcore's voxel boundaries, so earcore's grid keeps ~50 % more voxels here. So that
outlier removal runs on the same points, open3d's is timed on earcore's grid (open3d
counts a point among its own k neighbours, PCL and earcore do not: a few more kept).
Medians of `--repeats` runs; one thread, then all.

    python benches/bench_preprocess.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

import earcore

sys.path.insert(0, str(Path(__file__).parent))
from bench_perception import base_points, load_frames  # noqa: E402
from timing import median_time  # noqa: E402


def earcore_stages(points: np.ndarray, repeats: int) -> dict[str, float]:
    cropped = earcore.crop(points, center=np.zeros(3), radius=1.5)
    grid = earcore.voxel_downsample(cropped, 0.02)
    times = {
        "crop": median_time(lambda: earcore.crop(points, center=np.zeros(3), radius=1.5), repeats)[0],
        "voxel grid": median_time(lambda: earcore.voxel_downsample(cropped, 0.02), repeats)[0],
        "outliers": median_time(lambda: earcore.remove_statistical_outliers(grid, 20, 2.0), repeats)[0],
    }
    kept = earcore.remove_statistical_outliers(grid, 20, 2.0)
    times["points"] = (len(points), len(cropped), len(grid), len(kept))
    return times


def open3d_stages(points: np.ndarray, repeats: int) -> dict[str, float] | None:
    try:
        import open3d as o3d
    except ImportError:
        return None
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

    def crop() -> np.ndarray:
        return points[np.einsum("ij,ij->i", points, points) <= 1.5**2]

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(crop()))
    same = earcore.voxel_downsample(crop(), 0.02)
    grid = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(same))
    times = {
        "crop": median_time(crop, repeats)[0],
        "voxel grid": median_time(lambda: cloud.voxel_down_sample(0.02), repeats)[0],
        "outliers": median_time(lambda: grid.remove_statistical_outlier(20, 2.0), repeats)[0],
    }
    kept = grid.remove_statistical_outlier(20, 2.0)[0]
    times["points"] = (len(points), len(cloud.points), len(cloud.voxel_down_sample(0.02).points), len(kept.points))
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    points = base_points(load_frames(), 0, 0)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; one 512×424 frame, {len(points):,} valid points")
    print("\n| | threads | crop ms | voxel grid ms | outliers ms | total ms | points: frame → crop → grid → kept (open3d: kept of earcore's grid) |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for threads in (1, 0):
        earcore.set_num_threads(threads)
        rows.append(("earcore", "1" if threads == 1 else str(os.cpu_count()), earcore_stages(points, args.repeats)))
    peer = open3d_stages(points, args.repeats)
    if peer is not None:
        rows.append(("open3d-cpu", "its own", peer))
    for name, threads, t in rows:
        total = t["crop"] + t["voxel grid"] + t["outliers"]
        counts = " → ".join(f"{n:,}" for n in t["points"])
        print(f"| {name} | {threads} | {1e3 * t['crop']:.2f} | {1e3 * t['voxel grid']:.2f} | "
              f"{1e3 * t['outliers']:.2f} | {1e3 * total:.2f} | {counts} |")
    print("\ntarget: crop + voxel grid + outlier removal of a 512×424 frame <= 5 ms")
    earcore.set_num_threads(0)


if __name__ == "__main__":
    main()
