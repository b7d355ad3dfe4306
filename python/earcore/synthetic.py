"""Synthetic depth cameras looking at analytic shapes.

Tests, benchmarks and the map demo need depth frames whose geometry is known
exactly; these are rendered by intersecting each pixel's ray with spheres, boxes
and a floor (whole-array numpy, one pass per shape).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class DepthCamera:
    """Pinhole depth camera; defaults are Kinect V2-like (512×424, ~70°×60°)."""

    width: int = 512
    height: int = 424
    fx: float = 365.0
    fy: float = 365.0
    cx: float = 256.0
    cy: float = 212.0
    max_depth: float = 4.5

    def ray_directions(self) -> np.ndarray:
        """Unit rays (H·W, 3) in the camera frame (x right, y down, z forward)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        return d / np.linalg.norm(d, axis=1, keepdims=True)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`base_from_camera` (4×4) for a camera at `eye` looking at `target` (z forward, y down)."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance along unit rays `d` from `o` to the first hit (inf if none)."""
        oc = o - np.asarray(self.center)
        b = d @ oc
        c = oc @ oc - self.radius**2
        disc = b * b - c
        t = np.full(len(d), np.inf)
        ok = disc >= 0
        sq = np.sqrt(disc[ok])
        t0, t1 = -b[ok] - sq, -b[ok] + sq
        t[ok] = np.where(t0 > 1e-9, t0, np.where(t1 > 1e-9, t1, np.inf))
        return t


@dataclass(frozen=True)
class Box:
    """Axis-aligned box."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (np.asarray(self.lo) - o) * inv
            t2 = (np.asarray(self.hi) - o) * inv
        tnear = np.nanmax(np.minimum(t1, t2), axis=1)
        tfar = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tfar >= np.maximum(tnear, 0.0)) & (tfar > 1e-9)
        return np.where(hit, np.where(tnear > 1e-9, tnear, tfar), np.inf)


@dataclass(frozen=True)
class Floor:
    z: float = 0.0

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.z - o[2]) / d[:, 2]
        return np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)


@dataclass
class Scene:
    shapes: list = field(default_factory=list)

    def depth_points(self, camera: DepthCamera, base_from_camera: np.ndarray) -> np.ndarray:
        """World points (N, 3) seen by the camera (pixels with no hit within range dropped)."""
        d = camera.ray_directions() @ base_from_camera[:3, :3].T
        o = base_from_camera[:3, 3]
        t = np.full(len(d), np.inf)
        for s in self.shapes:
            t = np.minimum(t, s.intersect(o, d))
        # Depth (z in the camera frame) limits the range, as on a real sensor.
        z_cam = t * (camera.ray_directions()[:, 2])
        keep = np.isfinite(t) & (z_cam <= camera.max_depth)
        return o + d[keep] * t[keep, None]


def random_scene(rng: np.random.Generator, n_shapes: int = 8, extent: float = 1.5) -> Scene:
    """A floor plus random spheres and boxes inside ±`extent` m around the origin."""
    shapes: list = [Floor(0.0)]
    for _ in range(n_shapes):
        c = rng.uniform([-extent, -extent, 0.1], [extent, extent, 1.2])
        if rng.random() < 0.5:
            shapes.append(Sphere(tuple(c), float(rng.uniform(0.05, 0.4))))
        else:
            h = rng.uniform(0.05, 0.35, size=3)
            shapes.append(Box(tuple(c - h), tuple(c + h)))
    return Scene(shapes)
