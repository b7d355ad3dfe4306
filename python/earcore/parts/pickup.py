"""Pickup points from the detector's activations, as the papers pick: a class channel's
activation-weighted centroid when the class is on the platform once; with k parts of a
class (known, as in RoboCup@Work, where the task names them), k-means over the pixels
weighted by their activation, each cluster's weighted centroid a pickup point. The
gripper closes across the cluster's dominant axis (its weighted covariance's main
eigenvector)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Pick", "pickup_points", "weighted_kmeans"]


@dataclass(frozen=True)
class Pick:
    """One part found: class index, pickup point (u, v) px, the dominant axis's angle in
    the image (rad, from +u towards +v; the gripper closes across it) and the cluster's
    activation mass."""

    cls: int
    u: float
    v: float
    axis: float
    mass: float


def weighted_kmeans(points: np.ndarray, weights: np.ndarray, k: int, iterations: int = 20) -> np.ndarray:
    """(k,) cluster label per point (n, 2) for weights (n,) >= 0: seeds by weighted
    farthest-point (the heaviest point first, then the point of largest weight × squared
    distance to the seeds), then Lloyd's iterations on the weighted means."""
    n = len(points)
    if k < 1 or n == 0:
        raise ValueError(f"weighted k-means needs k >= 1 and points, got k={k}, {n} points")
    w = np.maximum(np.asarray(weights, dtype=np.float64), 0.0)
    centres = [points[int(np.argmax(w))]]
    d2 = ((points - centres[0]) ** 2).sum(1)
    for _ in range(1, k):
        centres.append(points[int(np.argmax(w * d2))])
        d2 = np.minimum(d2, ((points - centres[-1]) ** 2).sum(1))
    c = np.array(centres, dtype=np.float64)
    labels = np.zeros(n, dtype=np.int64)
    for _ in range(iterations):
        labels = ((points[:, None, :] - c[None]) ** 2).sum(-1).argmin(1)
        mass = np.bincount(labels, weights=w, minlength=k)
        sums = np.stack([np.bincount(labels, weights=w * points[:, j], minlength=k) for j in range(2)], 1)
        new = np.where(mass[:, None] > 0, sums / np.maximum(mass, 1e-12)[:, None], c)
        if np.allclose(new, c):
            break
        c = new
    return labels


def pickup_points(activations: np.ndarray, counts: np.ndarray | list[int]) -> list[Pick]:
    """Picks for (C, H, W) activations given how many parts of each class to find."""
    a = np.asarray(activations, dtype=np.float64)
    _, h, w = a.shape
    v, u = np.mgrid[0:h, 0:w]
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
    picks = []
    for cls, k in enumerate(np.asarray(counts, dtype=np.int64)):
        if k <= 0:
            continue
        weights = a[cls].ravel()
        labels = np.zeros(len(pixels), dtype=np.int64) if k == 1 else weighted_kmeans(pixels, weights, int(k))
        for j in range(int(k)):
            wj = np.where(labels == j, weights, 0.0)
            mass = wj.sum()
            if mass <= 0:
                picks.append(Pick(cls, float("nan"), float("nan"), 0.0, 0.0))
                continue
            centre = (wj[:, None] * pixels).sum(0) / mass
            d = pixels - centre
            cov = (wj[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / mass
            evals, evecs = np.linalg.eigh(cov)
            main = evecs[:, int(np.argmax(evals))]
            picks.append(Pick(cls, float(centre[0]), float(centre[1]), float(np.arctan2(main[1], main[0])), float(mass)))
    return picks
