"""Systematic depth error of an RGB-D sensor (Paper I's "depth distortion"): a pixel at
true depth z reads z + offset + scale·z + radial·ρ²·z², where ρ² = ((u − cx)/fx)² +
((v − cy)/fy)² is fixed to the image (the error pattern moves with the pixel, not with
the scene). The simulation corrupts its depth images with it; calibration fits it from
the board; the perception loop takes it out again."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TERMS", "DepthBias", "radius2_grid", "radius2_of"]

#: The model's terms, in order.
TERMS = ("offset", "scale", "radial")


def radius2_grid(K: np.ndarray, width: int, height: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """ρ² of every pixel of a (height, width) image region whose first pixel is image
    pixel `origin` (u, v), for camera matrix K."""
    u = (np.arange(width) + origin[0] - K[0, 2]) / K[0, 0]
    v = (np.arange(height) + origin[1] - K[1, 2]) / K[1, 1]
    return v[:, None] ** 2 + u[None, :] ** 2


def radius2_of(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """ρ² of pixel positions (N, 2)."""
    pixels = np.asarray(pixels, dtype=np.float64)
    return ((pixels[:, 0] - K[0, 2]) / K[0, 0]) ** 2 + ((pixels[:, 1] - K[1, 2]) / K[1, 1]) ** 2


@dataclass(frozen=True)
class DepthBias:
    """The error model's three numbers: `offset` (m), `scale` (fraction of z) and
    `radial` (m at z = 1 m and ρ² = 1)."""

    offset: float = 0.0
    scale: float = 0.0
    radial: float = 0.0

    def error(self, z: np.ndarray, rho2: np.ndarray | float) -> np.ndarray:
        """What a pixel at true depth z and image radius ρ² reads too much (m)."""
        return self.offset + self.scale * z + self.radial * rho2 * np.square(z)

    def correct(self, measured: np.ndarray, rho2: np.ndarray | float) -> np.ndarray:
        """The true depth of measured depths (0 stays 0 = no return): z = m − error(z),
        solved by fixed-point iteration (the error changes by ~1 % of a change in z, so
        three rounds leave < 1e-8 m)."""
        measured = np.asarray(measured, dtype=np.float64)
        z = measured
        for _ in range(3):
            z = measured - self.error(z, rho2)
        return np.where(measured > 0, z, 0.0)

    @property
    def is_zero(self) -> bool:
        return self == DepthBias()

    def as_list(self) -> list[float]:
        return [self.offset, self.scale, self.radial]

    @classmethod
    def fit(
        cls, measured: np.ndarray, true: np.ndarray, rho2: np.ndarray, *, terms: tuple[str, ...] = TERMS, rounds: int = 2
    ) -> DepthBias:
        """Least squares of `measured − true` on the chosen `terms` of (1, z, ρ²·z²)
        over the samples (depths of the same points, measured and known; the others
        stay 0), dropping samples beyond 3σ of the residual once per round (a corner
        whose depth hit the board's edge)."""
        unknown = set(terms) - set(TERMS)
        if unknown or not terms:
            raise ValueError(f"terms must be some of {TERMS}, got {terms}")
        measured, true, rho2 = (np.asarray(a, dtype=np.float64).ravel() for a in (measured, true, rho2))
        keep = np.isfinite(measured) & np.isfinite(true) & np.isfinite(rho2) & (measured > 0)
        if keep.sum() < 10:
            raise ValueError(f"fitting a depth error needs at least 10 depths, got {int(keep.sum())}")
        columns = {"offset": np.ones_like(true), "scale": true, "radial": rho2 * true**2}
        A = np.stack([columns[t] for t in terms], axis=1)
        b = measured - true
        coef: np.ndarray = np.zeros(len(terms))
        for _ in range(rounds + 1):
            coef = np.linalg.lstsq(A[keep], b[keep], rcond=None)[0]
            residual = b - A @ coef
            sigma = residual[keep].std()
            keep &= np.abs(residual) <= 3 * sigma + 1e-6
        return cls(**{t: float(c) for t, c in zip(terms, coef)})
