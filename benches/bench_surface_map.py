"""SurfaceMap in NOctoSLAM's setting (a VLP-16-like lidar in the 8 × 8 × 3.5 m room), one thread:

1. map update (insert + propagate) of one 15k-point scan into a small map (one scan,
   ~10^4 points) and into a large one (~10^7 points from 667 scans all over the room):
   the update touches only its branches, so the two times should match (target: < 1.5×);
2. point-to-plane ICP per iteration for a 15k-point scan against the map of a 5 s
   hand-held episode, = (time of 11 iterations − time of 1) / 10 (points that stay in
   their leaf reuse their pair after the first iteration), and the whole 11-iteration
   alignment's time per iteration.

    python benches/bench_surface_map.py [--repeats 15] [--large-scans 667]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

import earcore
from earcore.lidar_odometry import OdometrySettings
from earcore.synthetic import handheld_trajectory, lidar_room, render_lidar_scan

sys.path.insert(0, str(Path(__file__).parent))
from bench_vs_octomap import median_time  # noqa: E402

SETTINGS = OdometrySettings()


def median_seconds(fn, repeats: int) -> float:
    return median_time(fn, repeats)[0]


def random_pose(rng: np.random.Generator) -> np.ndarray:
    pose = np.eye(4)
    yaw = rng.uniform(-np.pi, np.pi)
    pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    pose[:3, 3] = rng.uniform([-3.0, -3.0, 1.0], [3.0, 3.0, 2.8])
    return pose


def insert(surface: earcore.SurfaceMap, scan_in_room: np.ndarray, origin: np.ndarray, dynamic: bool) -> None:
    if dynamic:
        surface.insert(scan_in_room, origin, SETTINGS.beam_spacing, SETTINGS.max_leaf_size)
    else:
        surface.insert(scan_in_room)


def map_update_flatness(boxes: np.ndarray, large_scans: int, repeats: int) -> None:
    """The probe scan goes into (a) the map of one scan from the same pose, (b) that map
    plus `large_scans` − 1 scans of copies of the room placed 10 m apart (the map grows,
    the probe's neighbourhood does not), (c) `large_scans` scans all over the one room
    (the neighbourhood fills up too: nodes gain children and more of them pass the PCA)."""
    rng = np.random.default_rng(1)
    probe_pose = random_pose(rng)
    probe = render_lidar_scan(probe_pose, [], boxes, seed=10**6) @ probe_pose[:3, :3].T + probe_pose[:3, 3]
    first = render_lidar_scan(probe_pose, [], boxes, seed=0) @ probe_pose[:3, :3].T + probe_pose[:3, 3]
    poses = [random_pose(rng) for _ in range(large_scans - 1)]
    scans = [render_lidar_scan(p, [], boxes, seed=i + 1) @ p[:3, :3].T + p[:3, 3] for i, p in enumerate(poses)]
    side = int(np.ceil(np.sqrt(large_scans)))
    offsets = [np.array([10.0 * (1 + i % side), 10.0 * (i // side), 0.0]) for i in range(large_scans - 1)]
    maps = {
        "one scan": [(probe_pose[:3, 3], first)],
        "+ rooms elsewhere": [(probe_pose[:3, 3], first)]
        + [(p[:3, 3] + o, s + o) for p, s, o in zip(poses, scans, offsets)],
        "+ same room": [(probe_pose[:3, 3], first)] + [(p[:3, 3], s) for p, s in zip(poses, scans)],
    }
    for dynamic in (False, True):
        label = "dynamic leaf depth" if dynamic else "1 cm leaves"
        times = {}
        for name, content in maps.items():
            surface = earcore.SurfaceMap(SETTINGS.resolution, position_memory=SETTINGS.position_memory)
            for origin, points in content:
                insert(surface, points, origin, dynamic)
            count = sum(len(points) for _, points in content)
            times[name] = median_seconds(lambda: insert(surface, probe, probe_pose[:3, 3], dynamic), repeats)
            print(
                f"  {label}, {name}: map of {count:,} points ({surface.size():,} nodes): "
                f"insert + propagate of {len(probe):,} points {1e3 * times[name]:.2f} ms"
            )
        print(
            f"{label}: update time, large map / small map = {times['+ rooms elsewhere'] / times['one scan']:.2f} "
            f"(target: < 1.5); same room filled in: {times['+ same room'] / times['one scan']:.2f}"
        )


def icp_per_iteration(boxes: np.ndarray, repeats: int) -> None:
    rng = np.random.default_rng(2)
    truths = handheld_trajectory(rng, seconds=5.0)
    surface = earcore.SurfaceMap(SETTINGS.resolution, position_memory=SETTINGS.position_memory)
    for k, pose in enumerate(truths[:-1]):
        insert(surface, render_lidar_scan(pose, [], boxes, noise_sigma=0.015, seed=k) @ pose[:3, :3].T + pose[:3, 3],
               pose[:3, 3], True)
    last = truths[-1]
    scan = render_lidar_scan(last, [], boxes, noise_sigma=0.015, seed=99)
    guess = last.copy()
    guess[:3, 3] += [0.02, -0.01, 0.01]

    def run(iterations: int) -> None:
        earcore.icp_point_to_plane(
            scan, surface, guess, max_iterations=iterations, huber_delta=SETTINGS.huber_delta,
            max_correspondence_distance=SETTINGS.max_correspondence_distance,
            translation_tolerance=0.0, rotation_tolerance=0.0, sigma_tolerance=0.0,
        )

    one, eleven = median_seconds(lambda: run(1), repeats), median_seconds(lambda: run(11), repeats)
    per_iteration = (eleven - one) / 10
    print(
        f"ICP, {len(scan):,}-point lidar scan against the map of a 5 s episode ({surface.size():,} nodes): "
        f"{1e3 * per_iteration:.2f} ms per iteration after the first, a call of one iteration {1e3 * one:.2f} ms, "
        f"11 iterations {1e3 * eleven / 11:.2f} ms per iteration all in (target: <= 1 ms; NOctoSLAM: 1.8 ms)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--large-scans", type=int, default=667, help="scans in the large map (667 ≈ 10^7 points)")
    args = parser.parse_args()
    earcore.set_num_threads(1)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; one thread")
    boxes = lidar_room(np.random.default_rng(0))
    icp_per_iteration(boxes, args.repeats)
    map_update_flatness(boxes, args.large_scans, args.repeats)


if __name__ == "__main__":
    main()
