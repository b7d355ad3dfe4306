"""Depth sensor models: intrinsics, range, rate and a noise model per camera type.

The noise models follow the sensors' published behaviour (axial noise growing with
distance and with the angle of incidence, dropouts at depth edges and grazing angles,
quantisation); the numbers are documented on each preset and checked by the tests.

* Kinect V2 (time of flight, 512×424, 70.6°×60°, 0.5-4.5 m): axial σ(z, θ) =
  1.5 − 0.5 z + 0.3 z² + 0.1 z^1.5 θ²/(π/2 − θ)² mm (Fankhauser et al. 2015, "Kinect v2
  for mobile robot navigation: evaluation and modeling"), depth delivered in whole mm.
* Kinect V1 (structured light, 320×240 here, 57°×43°, 0.4-4.5 m): axial σ(z, θ) =
  1.2 + 1.9 (z − 0.4)² mm for θ < 60°, plus 0.1 θ²/(√z (π/2 − θ)²) mm beyond (Nguyen,
  Izadi and Lovell 2012, "Modeling Kinect sensor noise"); depth quantised in disparity
  steps of 1/8 pixel of its native 640-pixel disparity image (f ≈ 580 px) with a 7.5 cm
  baseline: steps of z²/348 m (1.1 cm at 2 m), as Khoshelham and Elberink (2012) report.
* RealSense F200 (coded light, 640×480, 73°×59°, 0.2-1.2 m): axial σ(z) = 0.5 + 2.5 z² mm
  (an assumption matching its datasheet's ~1 mm at 0.5 m), whole-mm depth.

Every model drops pixels at depth discontinuities (a neighbour more than `edge_jump`
away) with probability `edge_dropout`, beyond `max_incidence` from the surface normal,
and outside [near, far].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = ["SENSORS", "SensorModel"]


@dataclass(frozen=True)
class SensorModel:
    name: str
    width: int
    height: int
    #: Horizontal and vertical field of view (degrees); the focal lengths follow.
    fov_h_deg: float
    fov_v_deg: float
    near: float
    far: float
    rate_hz: float
    #: Axial noise model: "tof" (Kinect V2), "structured" (Kinect V1) or "coded" (F200).
    noise: str
    #: Projector-camera baseline (m) of a structured-light sensor: depth is quantised in
    #: disparity steps of 1/8 pixel of the native disparity image (focal length
    #: `disparity_focal` px): steps of z² / (8 f b). 0: no disparity steps.
    baseline: float = 0.0
    disparity_focal: float = 0.0
    #: Depth delivered in steps of this many metres (0: continuous).
    depth_step: float = 0.001
    edge_jump: float = 0.05
    edge_dropout: float = 0.5
    max_incidence_deg: float = 80.0

    @property
    def fx(self) -> float:
        return 0.5 * self.width / math.tan(math.radians(self.fov_h_deg) / 2)

    @property
    def fy(self) -> float:
        return 0.5 * self.height / math.tan(math.radians(self.fov_v_deg) / 2)

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2

    @property
    def intrinsics(self) -> np.ndarray:
        """The 3×3 camera matrix K (OpenCV convention: pixel (u, v) centred at (u, v))."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, factor: float) -> SensorModel:
        """The same sensor at a fraction of the resolution (for quick runs)."""
        return replace(self, width=max(8, round(self.width * factor)), height=max(8, round(self.height * factor)))

    def sigma(self, z: np.ndarray, incidence: np.ndarray | float = 0.0) -> np.ndarray:
        """Axial noise standard deviation (m) at depth z (m) and incidence angle (rad)."""
        z = np.asarray(z, dtype=np.float64)
        theta = np.minimum(np.asarray(incidence, dtype=np.float64), np.radians(89.0))
        grazing = theta**2 / (np.pi / 2 - theta) ** 2
        if self.noise == "tof":
            mm = 1.5 - 0.5 * z + 0.3 * z**2 + 0.1 * z**1.5 * grazing
        elif self.noise == "structured":
            mm = 1.2 + 1.9 * (z - 0.4) ** 2 + np.where(theta > np.radians(60), 0.1 * grazing / np.sqrt(z), 0.0)
        elif self.noise == "coded":
            mm = 0.5 + 2.5 * z**2 + 0.0 * theta
        else:
            raise ValueError(f"unknown noise model {self.noise!r}")
        return mm * 1e-3

    def quantise(self, z: np.ndarray) -> np.ndarray:
        """What the sensor reports for true depth z: disparity steps and/or depth steps."""
        if self.baseline > 0:
            fb = (self.disparity_focal or self.fx) * self.baseline
            disparity = np.round(fb / np.maximum(z, 1e-6) * 8) / 8
            z = np.where(disparity > 0, fb / np.maximum(disparity, 1e-9), 0.0)
        if self.depth_step > 0:
            z = np.round(z / self.depth_step) * self.depth_step
        return z

    def corrupt(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Apply the noise model to a true depth image (0 = no return): axial noise by
        depth and incidence, dropouts at edges and grazing angles, range limits,
        quantisation. Returns the measured depth image (0 where invalid)."""
        z = np.asarray(depth, dtype=np.float64)
        valid = (z > 0) & np.isfinite(z)
        incidence = incidence_angles(z, self.fx, self.fy)
        noisy = z + rng.normal(size=z.shape) * self.sigma(np.where(valid, z, 1.0), np.nan_to_num(incidence))
        keep = valid & (incidence <= np.radians(self.max_incidence_deg))
        # Mixed pixels at depth edges: drop with some probability.
        jump = np.zeros_like(z, dtype=bool)
        for axis in (0, 1):
            d = np.abs(np.diff(np.where(valid, z, 0.0), axis=axis)) > self.edge_jump
            if axis == 0:
                jump[1:] |= d
                jump[:-1] |= d
            else:
                jump[:, 1:] |= d
                jump[:, :-1] |= d
        keep &= ~(jump & (rng.random(z.shape) < self.edge_dropout))
        measured = self.quantise(noisy)
        keep &= (measured >= self.near) & (measured <= self.far)
        return np.where(keep, measured, 0.0)


def incidence_angles(depth: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Angle between each pixel's viewing ray and the surface normal estimated from
    the depth image's gradients (NaN where a neighbour is missing)."""
    z = np.where(depth > 0, depth, np.nan)
    h, w = z.shape
    u = (np.arange(w) - (w - 1) / 2) / fx
    v = (np.arange(h) - (h - 1) / 2) / fy
    x = z * u[None, :]
    y = z * v[:, None]
    points = np.stack([x, y, z], axis=-1)
    du = np.gradient(points, axis=1)
    dv = np.gradient(points, axis=0)
    normal = np.cross(du, dv)
    norm = np.linalg.norm(normal, axis=-1)
    ray = points / np.linalg.norm(points, axis=-1, keepdims=True)
    cos = np.abs((normal * ray).sum(-1)) / np.where(norm > 0, norm, np.nan)
    return np.arccos(np.clip(cos, 0.0, 1.0))


#: The paper's cameras.
SENSORS: dict[str, SensorModel] = {
    "kinect_v2": SensorModel("kinect_v2", 512, 424, 70.6, 60.0, 0.5, 4.5, 30.0, "tof"),
    "kinect_v1": SensorModel(
        "kinect_v1", 320, 240, 57.0, 43.0, 0.4, 4.5, 30.0, "structured", baseline=0.075, disparity_focal=580.0, depth_step=0.001
    ),
    "f200": SensorModel("f200", 640, 480, 73.0, 59.0, 0.2, 1.2, 30.0, "coded"),
}
