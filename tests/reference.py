"""Independent references the tests share: synthetic scans of random scenes, OctoMap's
leaves through its own iterator, analytic box-face normals, Eq. 4 by brute force."""

from __future__ import annotations

import numpy as np

from earcore.synthetic import look_at, random_scene, render_depth_points

#: A small depth camera (160×120, ~70° wide) keeps the many-scene comparisons quick.
SMALL_CAMERA = dict(width=160, height=120, fx=114.0, fy=114.0, cx=80.0, cy=60.0)


def scene_scans(seed: int, n_views: int = 3, max_depth: float = 4.5) -> list[tuple[np.ndarray, np.ndarray]]:
    """Depth scans (points, origin) of one random scene of boxes and spheres on a floor,
    from `n_views` cameras around it."""
    rng = np.random.default_rng(seed)
    spheres, boxes = random_scene(rng, n_shapes=int(rng.integers(4, 12)))
    scans = []
    for _ in range(n_views):
        angle = rng.uniform(0, 2 * np.pi)
        eye = np.array([2.8 * np.cos(angle), 2.8 * np.sin(angle), rng.uniform(0.8, 2.2)])
        pose = look_at(eye, rng.uniform([-0.5, -0.5, 0.2], [0.5, 0.5, 0.8]))
        pts = render_depth_points(pose, spheres, boxes, 0.0, max_depth=max_depth, **SMALL_CAMERA)
        scans.append((pts, pose[:3, 3].copy()))
    return scans


def octomap_leaves(tree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OctoMap's leaves via its own iterator: float centres (M, 3), depths (M,), occupied (M,)."""
    centres, depths, occupied = [], [], []
    for it in tree.begin_leafs():
        centres.append(it.getCoordinate())
        depths.append(it.getDepth())
        occupied.append(tree.isNodeOccupied(it))
    return np.array(centres, dtype=np.float64).reshape(-1, 3), np.array(depths), np.array(occupied, dtype=bool)


def nearest_face_normals(points, boxes):
    """The unit normal (up to sign) of the axis-aligned box face nearest each point:
    the analytic reference for normals estimated from scans of box scenes."""
    points = np.asarray(points, dtype=np.float64)
    best = np.full(len(points), np.inf)
    axis = np.zeros(len(points), dtype=np.int64)
    for box in np.asarray(boxes, dtype=np.float64):
        lo, hi = box[:3], box[3:]
        clamped = np.clip(points, lo, hi)
        for a in range(3):
            for value in (lo[a], hi[a]):
                off = (points - clamped) ** 2
                off[:, a] = (points[:, a] - value) ** 2
                d = off.sum(axis=1)
                closer = d < best
                best[closer] = d[closer]
                axis[closer] = a
    return np.eye(3)[axis]


def motion_danger_reference(model, tree, q0, q1, resolution):
    """Eq. 4 as documented: per body, the mean over its axis points of Σ d (1 + C)."""
    steps = max(int(np.ceil(np.abs(q1 - q0).max() / resolution)), 1)
    path = q0 + np.linspace(0, 1, steps + 1)[:, None] * (q1 - q0)
    placed = [model.bodies(q) for q in path]
    total = 0.0
    for slot in range(len(placed[0]["link"])):
        length = np.linalg.norm(placed[0]["b"][slot] - placed[0]["a"][slot])
        n = max(int(np.ceil(length / tree.resolution)), 1)
        t = np.linspace(0, 1, n + 1)[:, None]
        points = np.stack([p["a"][slot] + t * (p["b"][slot] - p["a"][slot]) for p in placed])
        moves = np.linalg.norm(np.diff(points, axis=0), axis=-1)
        mid = 0.5 * (points[1:] + points[:-1])
        danger = tree.danger(mid.reshape(-1, 3)).reshape(moves.shape).astype(np.float64)
        total += (moves * (1 + danger)).sum() / (n + 1)
    return total
