"""Calibration's settings (Paper I's procedure, Algorithm 1): field names are the
keyword arguments of `CalibrationConfig`, which `Calibrator` takes whole."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["CalibrationConfig", "full_trajectory", "nominal_mount"]


def nominal_mount(extension: float = 0.10) -> np.ndarray:
    """flange_from_board as designed: the board's centre `extension` metres out along the
    flange's z axis, its printed face (z) facing the same way."""
    m = np.eye(4)
    m[2, 3] = extension
    return m



@dataclass
class CalibrationConfig:
    """Paper I's procedure: how the robot moves the board, what is fitted and what is refused."""


    #: flange_from_board as designed (the true mount differs a little; step 4 finds it).
    mount: np.ndarray = field(default_factory=nominal_mount)
    #: Depth frames per pose for the corners' depth (Paper I: median over 5).
    depth_frames: int = 5
    #: "median" (Paper I: 10-pixel neighbourhood) or "plane" (a plane fitted to the
    #: board's depth pixels, the corners' rays intersected with it).
    corner_method: str = "plane"
    #: Tilt limits: step (degrees), roll cap (Paper I: ±45°), pitch/yaw cap.
    tilt_step_deg: float = 5.0
    roll_limit_deg: float = 45.0
    tilt_limit_deg: float = 60.0
    #: The tilt search drives through waypoints this far apart (degrees).
    tilt_waypoint_deg: float = 22.5
    #: Tilt the board along the staged trajectory (fraction of each limit); 0: no tilting.
    tilt_fraction: float = 0.7
    #: Stages outward from the image centre: radius (fraction of the usable half-field
    #: of view) and positions per stage (Fig. 6).
    stage_radii: tuple[float, ...] = (0.0, 0.45, 0.85)
    stage_positions: tuple[int, ...] = (1, 4, 8)
    #: Where frames still missing after the stages are sought (Step 5b): radii and
    #: positions between the stages', each facing the camera, then turned halfway to
    #: the start pose's board; () seeks none.
    topup_radii: tuple[float, ...] = (0.3, 0.65)
    topup_positions: tuple[int, ...] = (4, 8)
    #: Their distances (multiples of the start pose's): wider than the stages', so that
    #: the focal length and the distance along the view separate.
    topup_distance_factors: tuple[float, ...] = (0.85, 1.4)
    #: Distances as multiples of the start pose's (Paper I: again 20 % farther).
    distance_factors: tuple[float, ...] = (1.0, 1.2)
    #: Stop a camera's trajectory after this many accepted frames (None: all).
    max_frames: int | None = None
    #: The initialisation sweep: board centre radius and height (m), board elevation
    #: (degrees above horizontal; more sweeps, higher up, for cameras not yet seen).
    sweep_radius: float = 0.5
    sweep_height: float = 0.55
    sweep_elevations_deg: tuple[float, ...] = (15.0, 55.0)
    #: Seconds between the cameras' looks while the robot moves (sweep, tilt search).
    watch_period: float = 0.1
    #: RRT-Connect time limit (s) for a motion whose straight path is blocked.
    plan_time: float = 0.5
    #: RANSAC inlier distance for the 3D-3D fits (m); while the lens is still unknown
    #: (during the trajectory) corners near the image's edge are off by centimetres, so
    #: those fits take the looser one.
    ransac_threshold: float = 0.01
    ransac_threshold_uncorrected: float = 0.03
    #: The final base_from_camera: "depth" (Paper I's 3D-3D fit of the depth corners,
    #: through the refined lens) or "pixels" (the lens fit's, the robot as the rig).
    pose_from: str = "depth"
    #: Lens model: "radial" (k1, k2, k3), "radial2" (k1, k2) or "full" (+ p1, p2). On
    #: the simulated Kinects, fitting the tangential terms too moves the principal point
    #: by pixels and the pose by millimetres.
    lens_model: str = "radial"
    #: A calibration whose corners reproject worse than this (pixels rms) is refused.
    max_reprojection_px: float = 1.0
    #: A camera whose pose is uncertain beyond this (`CameraCalibration.pose_sigma_m`,
    #: `pose_sigma_deg`, about 1σ) is refused (`PoorCalibration`) instead of written;
    #: None: no limit.
    max_pose_sigma_m: float | None = 0.005
    max_pose_sigma_deg: float | None = 0.5
    #: Passes of lens-and-pose from pixels / mount from depth in step 7.
    refinement_passes: int = 4
    #: The depth error's terms to fit (of offset + scale·z + radial·ρ²·z²,
    #: `earcore.depth_error`) from the corners' measured depth against where the robot
    #: and the pose from the pixels put them (Paper I's depth distortion), taken out
    #: before the final 3D-3D fit; () fits none.
    depth_error_terms: tuple[str, ...] = ("offset", "scale", "radial")
    seed: int = 0


def full_trajectory(settings: CalibrationConfig) -> CalibrationConfig:
    """The dense staged trajectory (more stages, more positions per stage: overlapping
    views, like Paper I's long runs) and no frame limit; the default trajectory is the
    sparse one that covers the field of view in ~30 frames."""
    return replace(settings, stage_radii=(0.0, 0.3, 0.55, 0.8), stage_positions=(1, 6, 8, 12), topup_radii=(), topup_positions=(), max_frames=None)
