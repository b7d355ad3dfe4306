"""From a segmented part in a depth camera's image to its pickup point in the robot's
base frame (through the camera's calibration, `CameraCalibration.base_from_camera`).

    pick = locate_part(belief, depth_m, (fx, fy, cx, cy), base_from_camera)
    pick.base      # (3,) m: the part's estimated centre of gravity in the base frame
    for pick, region in locate_parts(belief, depth_m, (fx, fy, cx, cy), base_from_camera): ...

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

__all__ = ["PartNotFound", "PickupPoint", "label_regions", "locate_part", "locate_parts"]


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
    others: np.ndarray | None = None,
) -> PickupPoint:
    """The pickup point of the part that `belief` (H, W) in [0, 1] segments in the
    depth image `depth_m` (H, W, metres, 0 = no return) of a camera with `intrinsics`
    (fx, fy, cx, cy) at `base_from_camera` (4x4). `others` (H, W) bool: pixels of other
    segmented parts, not counted as the support around this one."""
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
    if others is not None:
        around &= ~np.asarray(others, dtype=bool)
    if int(around.sum()) < 3:
        raise PartNotFound("no support visible around the part (it fills the image or has no depth around it)")
    sv, su = np.nonzero(around)
    support = float(np.median(_back_project(su.astype(float), sv.astype(float), depth[sv, su], intrinsics, pose)[:, 2]))
    top = float(np.percentile(points[:, 2], 90))
    height = max(top - support, 0.0)
    xy = (points[:, :2] * w[:, None]).sum(0) / w.sum()
    pixel = (float((u * w).sum() / w.sum()), float((v * w).sum() / w.sum()))
    return PickupPoint(np.array([xy[0], xy[1], support + height / 2]), pixel, height, int(mask.sum()))


def label_regions(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """(labels (H, W) int, count): the 4-connected regions of a boolean mask numbered
    1..count (0 outside), in the order of their first pixel (row-major). Each region
    takes its smallest pixel index by repeated whole-image neighbour minima (passes grow
    with a region's winding length, not its area)."""
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {mask.shape}")
    big = np.iinfo(np.int64).max
    labels = np.where(mask, np.arange(mask.size, dtype=np.int64).reshape(mask.shape), big)
    while True:
        low = labels.copy()
        np.minimum(low[1:], labels[:-1], out=low[1:])
        np.minimum(low[:-1], labels[1:], out=low[:-1])
        np.minimum(low[:, 1:], labels[:, :-1], out=low[:, 1:])
        np.minimum(low[:, :-1], labels[:, 1:], out=low[:, :-1])
        low = np.where(mask, low, big)
        # jump along the chain of smaller labels: fewer passes than one per pixel of the path
        flat = low.ravel()
        inside = flat != big
        flat[inside] = np.minimum(flat[inside], flat[flat[inside]])
        if np.array_equal(low, labels):
            break
        labels = low
    roots, numbered = np.unique(labels[mask], return_inverse=True)
    out = np.zeros(mask.shape, dtype=np.int64)
    out[mask] = numbered + 1
    return out, len(roots)


def locate_parts(
    belief: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Sequence[float],
    base_from_camera: np.ndarray,
    *,
    threshold: float = 0.5,
    min_pixels: int = 12,
) -> list[tuple[PickupPoint, np.ndarray]]:
    """Every part `belief` (H, W) segments: its 4-connected regions above `threshold` of
    at least `min_pixels` pixels, each located as by `locate_part` (the belief kept
    inside the region), with the region's mask; the biggest first. Parts that touch
    are one region: the count of parts is not known here (with counts known, the
    papers split a class's activation by k-means: `earcore.parts.pickup`)."""
    belief = np.asarray(belief, dtype=np.float64)
    segmented = belief > threshold
    labels, count = label_regions(segmented)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    out = []
    for region in np.argsort(-sizes[1:], kind="stable") + 1:
        if sizes[region] < min_pixels:
            break
        inside = labels == region
        try:
            pick = locate_part(np.where(inside, belief, 0.0), depth_m, intrinsics, base_from_camera, threshold=threshold, others=segmented)
            out.append((pick, inside))
        except PartNotFound:
            continue
    return out
