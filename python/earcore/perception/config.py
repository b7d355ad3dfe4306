"""The perception loop's settings (Paper II, Table I); field names are the TOML keys
of `[perception]` in `earcore run`'s configuration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from earcore.validate import ConfigError, count, finite, non_negative, one_of, positive, vector

__all__ = ["PerceptionConfig"]


@dataclass
class PerceptionConfig:
    #: Map frames per second (Paper II: 15, the Kinects' rate); faster cameras
    #: contribute their newest frame to each map frame.
    rate_hz: float = 15.0
    resolution: float = 0.05
    crop_radius: float = 1.5
    #: Points lower than this (m, base frame) only clear the space in front of them (free
    #: rays, no hit): the robot's table (its top at z = 0) is known geometry, added to
    #: the map by `PerceptionPipeline.add_support`, and sensed table points would fill
    #: the 5 cm voxels above the top with obstacles that the robot's shoulder brushes.
    #: None inserts every point as a hit.
    min_height: float | None = 0.02
    #: Rays of the points beyond `crop_radius` still clear the space inside the crop
    #: sphere (free rays cut where they leave it, no hit). Paper II drops those points
    #: outright, so space that cameras see only against a far background never decays.
    clear_beyond_crop: bool = True
    outlier_k: int = 20
    outlier_std_ratio: float = 2.0
    #: Voxel-grid size before insertion (m); 0 disables it.
    voxel_size: float = 0.02
    max_range: float = 4.5
    danger_alpha: float = 0.3
    decay_mode: Literal["observed", "always"] = "observed"
    #: Growth (m) of the robot's bodies for the self-filter on top of their padding, for
    #: sensor noise: with the Kinect V1's 1.1-1.3 cm depth steps at 2 m, Paper II's 5 mm
    #: alone leaves ~0.9 % of the robot's points in the map.
    self_filter_margin: float = 0.01
    #: A calibration file (`earcore calibrate`): the cameras it names use its poses and
    #: depth lenses instead of the simulation's ground truth. Empty: ground truth.
    calibration: str = ""
    #: Refine the camera poses once with ICP against each other (Paper II).
    refine_poses: bool = False
    #: Perturb the ground-truth camera poses by this much (m, rad) before use, to
    #: exercise the refinement; 0 = ground truth.
    pose_error: tuple[float, float] = (0.0, 0.0)

    def validate(self, where: str = "perception") -> PerceptionConfig:
        """Raise `ConfigError` naming the first setting out of its range; returns self."""
        positive(self.rate_hz, f"{where}.rate_hz", at_most=1000.0)
        positive(self.resolution, f"{where}.resolution", at_most=10.0)
        if self.resolution < 1e-4:
            raise ConfigError(f"{where}.resolution must be at least 0.0001 m (0.1 mm), got {self.resolution!r}")
        positive(self.crop_radius, f"{where}.crop_radius")
        if self.min_height is not None:
            finite(self.min_height, f"{where}.min_height")
        count(self.outlier_k, f"{where}.outlier_k")
        positive(self.outlier_std_ratio, f"{where}.outlier_std_ratio")
        non_negative(self.voxel_size, f"{where}.voxel_size")
        positive(self.max_range, f"{where}.max_range")
        non_negative(self.danger_alpha, f"{where}.danger_alpha")
        one_of(self.decay_mode, ("observed", "always"), f"{where}.decay_mode")
        non_negative(self.self_filter_margin, f"{where}.self_filter_margin")
        translation, rotation = vector(self.pose_error, f"{where}.pose_error", 2)
        non_negative(translation, f"{where}.pose_error[0]")
        non_negative(rotation, f"{where}.pose_error[1]")
        return self
