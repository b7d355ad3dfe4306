"""Zooming into part of an image: a box around some pixels, the image resampled into it,
and the intrinsics and pixels that go with the zoomed image. numpy only (the inference
path uses it without torch).

Coordinates: pixel centres at integers (OpenCV); a box is given in edge coordinates,
where source pixel i spans [i, i + 1), so a box (left, top, width, height) of a W×H image
covering all of it is (0, 0, W, H)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Box", "box_around", "crop", "crop_intrinsics", "crop_labels", "crop_pixels", "resample_matrix", "uncrop_pixels"]


@dataclass(frozen=True)
class Box:
    """A region of a source image in edge coordinates (see the module doc)."""

    left: float
    top: float
    width: float
    height: float

    def __post_init__(self) -> None:
        values = (self.left, self.top, self.width, self.height)
        if not all(math.isfinite(v) for v in values) or not (self.width > 0 and self.height > 0):
            raise ValueError(f"a box needs a finite corner and a size > 0, got left {self.left}, top {self.top}, width {self.width}, height {self.height}")

    @classmethod
    def whole(cls, width: int, height: int) -> Box:
        return cls(0.0, 0.0, float(width), float(height))

    def scale(self, out_size: tuple[int, int]) -> tuple[float, float]:
        """Output pixels per source pixel along x and y."""
        return out_size[0] / self.width, out_size[1] / self.height


def resample_matrix(n_in: int, n_out: int, start: float = 0.0, length: float | None = None) -> np.ndarray:
    """(n_out, n_in) weights that resample the source interval [start, start + length)
    (edge coordinates; default: all n_in pixels) onto n_out pixels: the box average over
    each output pixel's footprint when shrinking (length >= n_out), linear interpolation
    between pixel centres when growing. What lies outside the source contributes nothing
    (a zoom past the image's edge is black there)."""
    length = float(n_in if length is None else length)
    if n_in < 1 or n_out < 1 or not length > 0 or not math.isfinite(start) or not math.isfinite(length):
        raise ValueError(f"resample_matrix needs n_in, n_out >= 1 and a finite length > 0, got {n_in}, {n_out}, start {start}, length {length}")
    m = np.zeros((n_out, n_in))
    step = length / n_out
    if step >= 1.0:
        for o in range(n_out):
            lo, hi = start + o * step, start + (o + 1) * step
            for i in range(max(0, math.floor(lo)), min(n_in, math.ceil(hi))):
                m[o, i] = min(hi, i + 1) - max(lo, i)
        return m / step
    centres = start + (np.arange(n_out) + 0.5) * step - 0.5
    rows = np.nonzero((centres >= -0.5) & (centres <= n_in - 0.5))[0]
    c = np.clip(centres[rows], 0, n_in - 1)
    left = np.floor(c).astype(int)
    right = np.minimum(left + 1, n_in - 1)
    t = c - left
    np.add.at(m, (rows, left), 1 - t)
    np.add.at(m, (rows, right), t)
    return m


def _check_size(out_size: tuple[int, int]) -> tuple[int, int]:
    w, h = (int(v) for v in out_size)
    if w < 1 or h < 1:
        raise ValueError(f"the output size must be at least 1×1, got {out_size}")
    return w, h


def box_around(pixels: np.ndarray, image_size: tuple[int, int], out_size: tuple[int, int], *, margin: float = 0.25, min_width: float = 1.0) -> Box:
    """The box with the output's aspect ratio centred on the finite `pixels` (N, 2) that
    holds them with `margin` (a fraction of their extent) on every side, at least
    `min_width` source pixels wide; the whole image when no pixel is finite."""
    w_out, h_out = _check_size(out_size)
    uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    uv = uv[np.isfinite(uv).all(1)]
    if not len(uv):
        return Box.whole(*image_size)
    lo, hi = uv.min(0) + 0.5, uv.max(0) + 0.5  # edge coordinates of the pixel centres
    centre = 0.5 * (lo + hi)
    extent = (hi - lo) * (1.0 + 2.0 * margin)
    aspect = w_out / h_out
    width = max(float(extent[0]), float(extent[1]) * aspect, float(min_width), 1e-6)
    height = width / aspect
    return Box(float(centre[0] - width / 2), float(centre[1] - height / 2), width, height)


def crop(image: np.ndarray, box: Box, out_size: tuple[int, int]) -> np.ndarray:
    """(H, W) or (H, W, C) → (h, w[, C]) float32: `box` of the image resampled to `out_size`."""
    w, h = _check_size(out_size)
    height, width = image.shape[:2]
    rows = resample_matrix(height, h, box.top, box.height).astype(np.float32)
    cols = resample_matrix(width, w, box.left, box.width).astype(np.float32)
    src = np.asarray(image, dtype=np.float32)
    if src.ndim == 2:
        return rows @ src @ cols.T
    c = src.shape[2]
    tall = (rows @ src.reshape(height, width * c)).reshape(h, width, c)  # matrix products, not einsum: BLAS
    return np.ascontiguousarray((tall.transpose(0, 2, 1) @ cols.T).transpose(0, 2, 1))


def crop_labels(labels: np.ndarray, box: Box, out_size: tuple[int, int], outside: int = 0) -> np.ndarray:
    """(H, W) integer labels → (h, w): each output pixel takes the label under its centre
    (nearest), `outside` beyond the image."""
    w, h = _check_size(out_size)
    height, width = labels.shape[:2]
    sx, sy = box.scale((w, h))
    u = np.floor(box.left + (np.arange(w) + 0.5) / sx).astype(int)
    v = np.floor(box.top + (np.arange(h) + 0.5) / sy).astype(int)
    out = np.full((h, w), outside, dtype=labels.dtype)
    inside_u, inside_v = (u >= 0) & (u < width), (v >= 0) & (v < height)
    out[np.ix_(inside_v, inside_u)] = labels[np.ix_(v[inside_v], u[inside_u])]
    return out


def crop_pixels(pixels: np.ndarray, box: Box, out_size: tuple[int, int]) -> np.ndarray:
    """Source pixel coordinates (..., 2) → the zoomed image's."""
    sx, sy = box.scale(_check_size(out_size))
    uv = np.asarray(pixels, dtype=np.float64)
    return np.stack([(uv[..., 0] + 0.5 - box.left) * sx - 0.5, (uv[..., 1] + 0.5 - box.top) * sy - 0.5], -1)


def uncrop_pixels(pixels: np.ndarray, box: Box, out_size: tuple[int, int]) -> np.ndarray:
    """The zoomed image's pixel coordinates (..., 2) → the source's."""
    sx, sy = box.scale(_check_size(out_size))
    uv = np.asarray(pixels, dtype=np.float64)
    return np.stack([(uv[..., 0] + 0.5) / sx + box.left - 0.5, (uv[..., 1] + 0.5) / sy + box.top - 0.5], -1)


def crop_intrinsics(intrinsics: np.ndarray, box: Box, out_size: tuple[int, int]) -> np.ndarray:
    """The 3×3 intrinsics of the zoomed image: a point's projection through them is its
    source projection passed through `crop_pixels`."""
    sx, sy = box.scale(_check_size(out_size))
    k = np.asarray(intrinsics, dtype=np.float64)
    out = k.copy()
    out[0, 0], out[0, 1] = k[0, 0] * sx, k[0, 1] * sx
    out[1, 1] = k[1, 1] * sy
    out[0, 2] = (k[0, 2] + 0.5 - box.left) * sx - 0.5
    out[1, 2] = (k[1, 2] + 0.5 - box.top) * sy - 0.5
    return out
