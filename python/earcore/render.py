"""Images of triangle meshes from the core: `Rasterizer` (depth, labels and shaded
colour through a pinhole, exact geometry) and `PixelMap` (resampling a pinhole image
where a distorted lens's pixels land in it).

    raster = Rasterizer([(vertices, triangles, (0.8, 0.8, 0.8), label), ...])
    rgb, depth, label = raster.render(camera_from_mesh, K, width, height)
    lens = PixelMap(width, height, u, v)     # u, v: (H, W) where each output pixel reads
    rgb = lens.bilinear(rgb); depth = lens.depth(depth); label = lens.nearest(label)

Pixel (u, v) is centred at (u, v) and v points down (OpenCV's convention); depth is
along the optical axis, 0 where nothing lies between `near` and `far`; labels are -1
there.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from earcore import _earcore

__all__ = ["Light", "PixelMap", "Rasterizer"]


class Light:
    """Lambertian light: a surface shows `ambient` of its colour plus `diffuse` times
    the cosine between its normal (either side) and `direction` (towards the light,
    in the camera frame)."""

    def __init__(self, direction: Sequence[float] = (0.0, 0.0, -1.0), ambient: float = 0.55, diffuse: float = 0.45) -> None:
        self.direction = np.asarray(direction, dtype=np.float64)
        if self.direction.shape != (3,) or not np.isfinite(self.direction).all() or not self.direction.any():
            raise ValueError(f"light direction must be three finite numbers, not all zero, got {direction}")
        self.ambient, self.diffuse = float(ambient), float(diffuse)


class Rasterizer:
    """Meshes held once, drawn from any camera with any poses. `meshes`: a sequence of
    (vertices (N, 3), triangles (M, 3) indices, rgb (3,) in [0, 1], label int)."""

    def __init__(self, meshes: Sequence[tuple[np.ndarray, np.ndarray, Sequence[float], int]]) -> None:
        self._core = _earcore.Rasterizer(list(meshes))

    def __len__(self) -> int:
        return len(self._core)

    def render(
        self,
        camera_from_mesh: np.ndarray,
        K: np.ndarray,
        width: int,
        height: int,
        *,
        near: float = 0.05,
        far: float = 10.0,
        hidden: np.ndarray | None = None,
        light: Light | None = None,
        background: tuple[int, int, int] = (0, 0, 0),
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) uint8, depth (H, W) m, label (H, W) int64) of the meshes placed
        by `camera_from_mesh` (M, 4, 4), skipping those where `hidden` (M,) is true."""
        poses = np.ascontiguousarray(camera_from_mesh, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[0] != len(self):
            raise ValueError(f"camera_from_mesh must be ({len(self)}, 4, 4), one pose per mesh, got {poses.shape}")
        flags = np.zeros(len(self), bool) if hidden is None else np.asarray(hidden, dtype=bool)
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3×3, got {K.shape}")
        light = light or Light()
        return self._core.render(
            poses,
            flags.tolist(),
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            int(width),
            int(height),
            float(near),
            float(far),
            tuple(light.direction),
            light.ambient,
            light.diffuse,
            (int(background[0]), int(background[1]), int(background[2])),
        )


class PixelMap:
    """Where each output pixel samples a `source_width` × `source_height` image: `u`, `v`
    (H, W) in the source's pixel coordinates, clamped to its border."""

    def __init__(self, source_width: int, source_height: int, u: np.ndarray, v: np.ndarray) -> None:
        u = np.ascontiguousarray(u, dtype=np.float64)
        v = np.ascontiguousarray(v, dtype=np.float64)
        if u.ndim != 2 or u.shape != v.shape:
            raise ValueError(f"u and v must be (H, W) arrays of one shape, got {u.shape} and {v.shape}")
        self.shape = u.shape
        self._core = _earcore.PixelMap(int(source_width), int(source_height), u, v)

    def bilinear(self, image: np.ndarray) -> np.ndarray:
        """An 8-bit image (h, w) or (h, w, C), bilinearly resampled."""
        image = np.asarray(image)
        if image.dtype != np.uint8:
            raise TypeError(f"bilinear resamples uint8 images, got {image.dtype}")
        out = self._core.bilinear(np.ascontiguousarray(image.reshape(*image.shape[:2], -1)))
        return out.reshape(*self.shape, *image.shape[2:])

    def nearest(self, labels: np.ndarray) -> np.ndarray:
        """Integer labels (h, w), each output pixel the nearest sample's."""
        labels = np.asarray(labels)
        if labels.dtype.kind not in "iu" or (labels.dtype.kind == "u" and labels.dtype.itemsize == 8):
            raise TypeError(f"nearest resamples integer labels that fit int64, got {labels.dtype}")
        return self._core.nearest(np.ascontiguousarray(labels, dtype=np.int64))

    def depth(self, depth: np.ndarray, edge: float = 0.02) -> np.ndarray:
        """Depth (h, w; 0 = no return): inverse depth interpolated across one surface
        (neighbours valid and within `edge` m), the nearest sample at edges and holes."""
        return self._core.depth(np.ascontiguousarray(depth, dtype=np.float64), float(edge))
