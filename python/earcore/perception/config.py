"""The perception loop's settings (Paper II, Table I); field names are the TOML keys
of `[perception]` in `earcore run`'s configuration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

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
