"""Pictures of an estimate in the papers' convention (Paper V, Fig. 5): true joints as
green crosses, predicted joints as red circles, the predicted base as a magenta circle,
the predicted mask tinted. numpy only."""

from __future__ import annotations

import numpy as np

__all__ = ["GREEN", "MAGENTA", "RED", "draw_circle", "draw_cross", "overlay", "project"]

GREEN = (0, 220, 0)
RED = (230, 20, 20)
MAGENTA = (230, 0, 230)
TINT = (0, 120, 255)


def project(points: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(K, 3) camera-frame points → (K, 2) pixels (points behind the camera → NaN)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    k = np.asarray(intrinsics, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([k[0, 0] * p[:, 0] / z + k[0, 2], k[1, 1] * p[:, 1] / z + k[1, 2]], 1)
    uv[z <= 1e-6] = np.nan
    return uv


def _put(image: np.ndarray, xs: np.ndarray, ys: np.ndarray, colour: tuple[int, int, int]) -> None:
    xs, ys = np.rint(xs).astype(int), np.rint(ys).astype(int)
    inside = (xs >= 0) & (xs < image.shape[1]) & (ys >= 0) & (ys < image.shape[0])
    image[ys[inside], xs[inside]] = colour


def draw_circle(image: np.ndarray, centre: np.ndarray, radius: float, colour: tuple[int, int, int], thickness: int = 1) -> None:
    """An outlined circle, in place."""
    if not np.isfinite(centre).all():
        return
    steps = max(16, int(2 * np.pi * (radius + thickness) * 2))
    a = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    for r in np.arange(radius, radius + thickness, 1.0) if thickness > 1 else [radius]:
        _put(image, centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), colour)


def draw_cross(image: np.ndarray, centre: np.ndarray, size: float, colour: tuple[int, int, int]) -> None:
    """An × of half-size `size`, in place."""
    if not np.isfinite(centre).all():
        return
    t = np.linspace(-size, size, int(4 * size) + 1)
    _put(image, centre[0] + t, centre[1] + t, colour)
    _put(image, centre[0] + t, centre[1] - t, colour)


def overlay(
    image: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    predicted: np.ndarray | None = None,
    truth: np.ndarray | None = None,
    base: np.ndarray | None = None,
    radius: float | None = None,
    alpha: float = 0.4,
) -> np.ndarray:
    """A copy of `image` (H, W, 3) uint8 with the mask tinted, `truth` pixels (K, 2) as
    green crosses, `predicted` pixels (K, 2) as red circles and the `base` pixel (2,) as
    a magenta circle. Marks scale with the image (radius ≈ 1 % of its width, ≥ 2 px)."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
    out = img.copy()
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != img.shape[:2]:
            raise ValueError(f"mask must be {img.shape[:2]}, got {m.shape}")
        blend = (1 - alpha) * out[m].astype(np.float64) + alpha * np.asarray(TINT, dtype=np.float64)
        out[m] = np.clip(np.rint(blend), 0, 255).astype(np.uint8)
    r = radius if radius is not None else max(2.0, 0.012 * img.shape[1])
    thick = max(1, int(round(r / 4)))
    for point in np.asarray(truth if truth is not None else np.zeros((0, 2)), dtype=np.float64).reshape(-1, 2):
        draw_cross(out, point, r, GREEN)
    for point in np.asarray(predicted if predicted is not None else np.zeros((0, 2)), dtype=np.float64).reshape(-1, 2):
        draw_circle(out, point, r, RED, thick)
    if base is not None:
        draw_circle(out, np.asarray(base, dtype=np.float64).reshape(2), 1.3 * r, MAGENTA, thick)
    return out
