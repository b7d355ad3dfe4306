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
* RealSense SR300 (the F200's successor, coded light, 640×480, 71.5°×55°, 0.2-1.5 m):
  the F200's noise model; the parts camera of the IROS 2018 / AAMAS 2019 papers.
* A colour-only camera ("webcam", 640×480, 60°×46.8°, a USB camera's typical barrel lens
  k1 = −0.12, k2 = 0.08): no depth at all (`has_depth` is False; its frames carry an
  empty depth image). Calibration finds its pose from the board's image alone (AX = ZB).
* A machine-vision colour camera ("machine_vision", 2448×2048, 30°×25.3°, a mild barrel
  lens k1 = −0.05, k2 = 0.02): the charging station's stereo pair (Paper III).

Lenses (the ground truth calibration has to recover; OpenCV's Brown-Conrady model k1,
k2, p1, p2, k3): the Kinect V2's IR lens (0.09, −0.27, 0, 0, 0.09) is the typical
factory calibration libfreenect2 reads off the device; the Kinect V1's IR lens
(−0.10, 0.25) and colour lens (0.15, −0.35) are of the size Herrera, Kannala and
Heikkilä (2012, "Joint depth and color camera calibration with distortion correction")
report. Each Kinect has its colour camera beside the depth camera: 5.2 cm (V2) and
2.5 cm (V1) along x with a fraction of a degree of misalignment (`ColourSensor`).

Systematic depth error (`DepthBias`, what Paper I's step 7 calls depth distortion): the
sensor reports z + offset + scale·z + radial·ρ²·z², with ρ² = ((u − cx)/fx)² + ((v − cy)/fy)²
fixed to the image. The Kinect V2's (+3 mm, +6 mm radial: millimetres at the centre
growing toward the corners) and the Kinect V1's (+0.3 % of z, −6 mm radial: a scale error
of the disparity-to-depth conversion and a disparity pattern that grows with z²) are
assumptions of the size Lachat et al. (2015), Pagliari and Pinto (2015) and Herrera,
Kannala and Heikkilä (2012) report for the devices; calibration has to find them.

Every model drops pixels at depth discontinuities (a neighbour more than `edge_jump`
away) with probability `edge_dropout`, beyond `max_incidence` from the surface normal,
and outside [near, far].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from earcore.cloud import incidence_angles
from earcore.depth_error import DepthBias, radius2_grid
from earcore.transforms import rotation_xyz

__all__ = ["SENSORS", "ColourSensor", "DepthBias", "SensorModel", "radius2_grid"]


Distortion = tuple[float, float, float, float, float]
NO_DISTORTION: Distortion = (0.0, 0.0, 0.0, 0.0, 0.0)


def _focal(pixels: int, fov_deg: float) -> float:
    return 0.5 * pixels / math.tan(math.radians(fov_deg) / 2)


def _pinhole(width: int, height: int, fov_h_deg: float, fov_v_deg: float) -> np.ndarray:
    """K (OpenCV convention: pixel (u, v) centred at (u, v)) of a camera with these
    image size and fields of view."""
    fx, fy = _focal(width, fov_h_deg), _focal(height, fov_v_deg)
    return np.array([[fx, 0, (width - 1) / 2], [0, fy, (height - 1) / 2], [0, 0, 1.0]])


@dataclass(frozen=True)
class ColourSensor:
    """The colour camera of an RGB-D sensor: its own pinhole, lens and pose relative to
    the depth (IR) camera (`depth_from_colour`: translation in m, then rotation as
    x-y-z Euler angles in degrees)."""

    width: int
    height: int
    fov_h_deg: float
    fov_v_deg: float
    distortion: Distortion = NO_DISTORTION
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def intrinsics(self) -> np.ndarray:
        return _pinhole(self.width, self.height, self.fov_h_deg, self.fov_v_deg)

    @property
    def depth_from_colour(self) -> np.ndarray:
        """4×4 pose of the colour camera in the depth camera's frame."""
        m = np.eye(4)
        m[:3, :3] = rotation_xyz(*np.radians(self.rotation_deg))
        m[:3, 3] = self.translation
        return m

    def scaled(self, factor: float) -> ColourSensor:
        return replace(self, width=max(8, round(self.width * factor)), height=max(8, round(self.height * factor)))


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
    #: Axial noise model: "tof" (Kinect V2), "structured" (Kinect V1), "coded" (F200),
    #: or "none" for a camera without depth.
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
    #: The IR/depth lens (OpenCV's k1, k2, p1, p2, k3): depth and IR images are distorted.
    distortion: Distortion = NO_DISTORTION
    #: The colour camera beside the depth camera; None: colour comes from the depth
    #: camera's own view (a registered image).
    colour: ColourSensor | None = None
    #: Systematic depth error (depth distortion); the noise is added on top.
    depth_bias: DepthBias = DepthBias()

    @property
    def has_depth(self) -> bool:
        return self.noise != "none"

    @property
    def fx(self) -> float:
        return _focal(self.width, self.fov_h_deg)

    @property
    def fy(self) -> float:
        return _focal(self.height, self.fov_v_deg)

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2

    @property
    def intrinsics(self) -> np.ndarray:
        """The 3×3 camera matrix K (OpenCV convention: pixel (u, v) centred at (u, v))."""
        return _pinhole(self.width, self.height, self.fov_h_deg, self.fov_v_deg)

    def scaled(self, factor: float) -> SensorModel:
        """The same sensor at a fraction of the resolution (for quick runs)."""
        colour = None if self.colour is None else self.colour.scaled(factor)
        return replace(
            self, width=max(8, round(self.width * factor)), height=max(8, round(self.height * factor)), colour=colour
        )

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
        elif self.noise == "none":
            mm = 0.0 * z * theta
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

    def corrupt(self, depth: np.ndarray, rng: np.random.Generator, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Apply the systematic error and the noise model to a true depth image (0 = no
        return): axial noise by depth and incidence, dropouts at edges and grazing
        angles, range limits, quantisation. Returns the measured depth image (0 where
        invalid). `depth` may be a region of the image whose first pixel is `origin`."""
        z = np.asarray(depth, dtype=np.float64)
        if not self.has_depth:
            return np.zeros_like(z)
        valid = (z > 0) & np.isfinite(z)
        incidence = incidence_angles(z, self.fx, self.fy)
        biased = z
        if not self.depth_bias.is_zero:
            biased = z + self.depth_bias.error(z, radius2_grid(self.intrinsics, z.shape[1], z.shape[0], origin))
        # float32 draws: half the time of float64 ones, far finer than any σ here.
        noisy = biased + rng.standard_normal(z.shape, dtype=np.float32) * self.sigma(np.where(valid, z, 1.0), np.nan_to_num(incidence))
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
        dropped = np.zeros_like(jump)
        dropped[jump] = rng.random(int(jump.sum())) < self.edge_dropout
        keep &= ~dropped
        measured = self.quantise(noisy)
        keep &= (measured >= self.near) & (measured <= self.far)
        return np.where(keep, measured, 0.0)


#: The paper's cameras.
SENSORS: dict[str, SensorModel] = {
    "kinect_v2": SensorModel(
        "kinect_v2", 512, 424, 70.6, 60.0, 0.5, 4.5, 30.0, "tof",
        distortion=(0.09, -0.27, 0.0, 0.0, 0.09),
        colour=ColourSensor(1920, 1080, 84.1, 53.8, (0.03, -0.05, 0.0, 0.0, 0.0), (0.052, 0.0, 0.0), (0.3, -0.2, 0.1)),
        depth_bias=DepthBias(offset=0.003, radial=0.006),
    ),
    "kinect_v1": SensorModel(
        "kinect_v1", 320, 240, 57.0, 43.0, 0.4, 4.5, 30.0, "structured", baseline=0.075, disparity_focal=580.0, depth_step=0.001,
        distortion=(-0.10, 0.25, 0.0, 0.0, 0.0),
        colour=ColourSensor(640, 480, 62.0, 48.6, (0.15, -0.35, 0.0, 0.0, 0.0), (0.025, 0.0, 0.0), (-0.2, 0.3, 0.0)),
        depth_bias=DepthBias(scale=0.003, radial=-0.006),
    ),
    "f200": SensorModel("f200", 640, 480, 73.0, 59.0, 0.2, 1.2, 30.0, "coded"),
    "sr300": SensorModel("sr300", 640, 480, 71.5, 55.0, 0.2, 1.5, 30.0, "coded"),
    "webcam": SensorModel("webcam", 640, 480, 60.0, 46.8, 0.1, 5.0, 30.0, "none", distortion=(-0.12, 0.08, 0.0, 0.0, 0.0)),
    # a 5-megapixel machine-vision camera (2/3" sensor, 3.45 µm pixels) with a 16 mm lens
    "machine_vision": SensorModel("machine_vision", 2448, 2048, 30.0, 25.3, 0.3, 6.0, 10.0, "none", distortion=(-0.05, 0.02, 0.0, 0.0, 0.0)),
}
