"""From a segmented part in a depth camera's image to its pickup point in the robot's
base frame (through the camera's calibration, `CameraCalibration.base_from_camera`).

    pick = locate_part(belief, depth_m, (fx, fy, cx, cy), base_from_camera)
    pick.base      # (3,) m: the part's estimated centre of gravity in the base frame

The part's pixels (belief > threshold, with a depth) are back-projected and moved into
the base frame. The pickup point's x, y is the belief-weighted mean of those points
(the visible top, which lies over the centre of gravity for parts lying on a face);
its height is halfway between the support under the part (the median height of a ring
of pixels around it) and the part's top (the 90th percentile of its points), the
centre of gravity of a part of uniform section lying down. The base frame's z axis
must point up (as a robot standing on the floor's does).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from earcore.errors import EarcoreError

__all__ = ["PartNotFound", "PickupPoint", "locate_part"]


class PartNotFound(EarcoreError, ValueError):
    """The segmentation holds no pixel with a depth (or no support around it)."""


@dataclass(frozen=True)
class PickupPoint:
    base: np.ndarray
    #: The belief-weighted centroid (u, v), px.
    pixel: tuple[float, float]
    #: The part's height above its support, m.
    height: float
    pixels: int


def _back_project(u: np.ndarray, v: np.ndarray, z: np.ndarray, k: Sequence[float], base_from_camera: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy = (float(x) for x in k)
    camera = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    return camera @ base_from_camera[:3, :3].T + base_from_camera[:3, 3]


def locate_part(
    belief: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Sequence[float],
    base_from_camera: np.ndarray,
    *,
    threshold: float = 0.5,
    ring: int = 3,
) -> PickupPoint:
    """The pickup point of the part that `belief` (H, W) in [0, 1] segments in the
    depth image `depth_m` (H, W, metres, 0 = no return) of a camera with `intrinsics`
    (fx, fy, cx, cy) at `base_from_camera` (4x4)."""
    belief, depth = np.asarray(belief, dtype=np.float64), np.asarray(depth_m, dtype=np.float64)
    if belief.shape != depth.shape or belief.ndim != 2:
        raise ValueError(f"belief {belief.shape} and depth {depth.shape} must be the same (H, W)")
    pose = np.asarray(base_from_camera, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"base_from_camera must be 4x4, got {pose.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    mask = (belief > threshold) & valid
    if int(mask.sum()) < 3:
        raise PartNotFound(f"the segmentation holds {int(mask.sum())} pixel(s) with a depth; no part to pick")
    v, u = np.nonzero(mask)
    w = belief[v, u]
    points = _back_project(u.astype(float), v.astype(float), depth[v, u], intrinsics, pose)
    # the support: pixels within `ring` px of the part but not of it
    grown = mask.copy()
    for _ in range(ring):
        g = grown.copy()
        g[1:] |= grown[:-1]
        g[:-1] |= grown[1:]
        g[:, 1:] |= grown[:, :-1]
        g[:, :-1] |= grown[:, 1:]
        grown = g
    around = grown & ~(belief > threshold) & valid
    if int(around.sum()) < 3:
        raise PartNotFound("no support visible around the part (it fills the image or has no depth around it)")
    sv, su = np.nonzero(around)
    support = float(np.median(_back_project(su.astype(float), sv.astype(float), depth[sv, su], intrinsics, pose)[:, 2]))
    top = float(np.percentile(points[:, 2], 90))
    height = max(top - support, 0.0)
    xy = (points[:, :2] * w[:, None]).sum(0) / w.sum()
    pixel = (float((u * w).sum() / w.sum()), float((v * w).sum() / w.sum()))
    return PickupPoint(np.array([xy[0], xy[1], support + height / 2]), pixel, height, int(mask.sum()))
