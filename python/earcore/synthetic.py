"""Synthetic depth frames of analytic scenes (rendered in Rust), for tests, demos and
benchmarks: the geometry behind every point is known exactly."""

from __future__ import annotations

import numpy as np

from earcore._earcore import benchmark_frame, render_depth_points, render_lidar_scan, robot_cell_voxels
from earcore.transforms import look_at, rotation_xyz

__all__ = [
    "benchmark_frame",
    "handheld_trajectory",
    "lidar_room",
    "look_at",
    "random_scene",
    "render_depth_points",
    "render_lidar_scan",
    "robot_cell_voxels",
]


def random_scene(rng: np.random.Generator, n_shapes: int = 8, extent: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Random spheres (K, 4) and axis-aligned boxes (K, 6) within ±`extent` m (z in [0.1, 1.2])."""
    centres = rng.uniform([-extent, -extent, 0.1], [extent, extent, 1.2], size=(n_shapes, 3))
    is_sphere = rng.random(n_shapes) < 0.5
    spheres = np.column_stack([centres[is_sphere], rng.uniform(0.05, 0.4, is_sphere.sum())])
    half = rng.uniform(0.05, 0.35, size=(int((~is_sphere).sum()), 3))
    boxes = np.column_stack([centres[~is_sphere] - half, centres[~is_sphere] + half])
    return spheres.reshape(-1, 4), boxes.reshape(-1, 6)


def lidar_room(rng: np.random.Generator, n_boxes: int = 12) -> np.ndarray:
    """NOctoSLAM's test room: an 8 × 8 × 3.5 m room (the first box, seen from inside)
    with furniture-sized boxes standing on its floor. Returns boxes (K, 6)."""
    room = [-4.0, -4.0, 0.0, 4.0, 4.0, 3.5]
    size = rng.uniform([0.3, 0.3, 0.4], [1.5, 1.2, 2.0], size=(n_boxes, 3))
    corner = rng.uniform([-3.9, -3.9], [3.9, 3.9], size=(n_boxes, 2)) - size[:, :2] / 2
    furniture = np.column_stack([corner, np.zeros(n_boxes), corner + size[:, :2], size[:, 2]])
    return np.vstack([room, furniture])


def handheld_trajectory(
    rng: np.random.Generator, seconds: float, rate_hz: float = 20.0, speed: float = 0.5
) -> list[np.ndarray]:
    """A lidar carried by hand through `lidar_room` above the furniture (NOctoSLAM's
    episodes): a smooth Catmull-Rom path through random waypoints at walking `speed`
    (m/s), yaw sweeping, a few degrees of roll and pitch. One 4×4 `room_from_sensor`
    per scan at `rate_hz`, sensor z up."""
    waypoints = rng.uniform([-2.8, -2.8, 2.2], [2.8, 2.8, 2.8], size=(int(seconds / 4) + 4, 3))
    u = np.linspace(0, 1, 200, endpoint=False)[:, None]
    fine = []
    for i in range(1, len(waypoints) - 2):
        p0, p1, p2, p3 = waypoints[i - 1 : i + 3]
        fine.append(
            0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3)
        )
    path = np.vstack(fine)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    n = int(seconds * rate_hz)
    s = np.minimum(np.arange(n) * speed / rate_hz, arc[-1])
    positions = np.column_stack([np.interp(s, arc, path[:, a]) for a in range(3)])
    t = np.arange(n) / rate_hz
    phase = rng.uniform(0, 2 * np.pi, 4)
    yaw = 0.6 * np.sin(0.25 * t + phase[0]) + 0.4 * np.sin(0.11 * t + phase[1])
    roll = np.radians(4) * np.sin(0.7 * t + phase[2])
    pitch = np.radians(4) * np.sin(0.5 * t + phase[3])
    poses = []
    for k in range(n):
        m = np.eye(4)
        m[:3, :3] = rotation_xyz(roll[k], pitch[k], yaw[k])
        m[:3, 3] = positions[k]
        poses.append(m)
    return poses
