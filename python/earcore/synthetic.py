"""Synthetic depth frames of analytic scenes (rendered in Rust), for tests, demos and
benchmarks: the geometry behind every point is known exactly."""

from __future__ import annotations

import numpy as np

from earcore._earcore import benchmark_frame, render_depth_points, render_lidar_scan, robot_cell_voxels

__all__ = [
    "benchmark_frame",
    "lidar_room",
    "look_at",
    "random_scene",
    "render_depth_points",
    "render_lidar_scan",
    "robot_cell_voxels",
]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`base_from_camera` (4×4) of a camera at `eye` looking at `target` (z forward, y down)."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: any perpendicular will do
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(z, x), z, eye
    return pose


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
