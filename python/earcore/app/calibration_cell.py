"""Calibration in the simulated cell: a cell whose cameras stand away from their
nominal places and whose board sits a little off its designed mount (the truth kept for
evaluation only), and the errors of a calibration against that truth."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from earcore.calibration.board import Checkerboard
from earcore.calibration.config import nominal_mount
from earcore.calibration.eye_to_hand import apply_pose, rotation_spread_deg
from earcore.calibration.intrinsics import lens_displacement
from earcore.calibration.store import CameraCalibration
from earcore.depth_error import radius2_of
from earcore.sim.config import CellConfig, calibration_cameras
from earcore.transforms import perturb_pose

__all__ = ["CalibrationErrors", "calibration_cell", "calibration_cell_config", "evaluate"]


def calibration_cell_config(seed: int = 0, camera_scale: float = 1.0) -> CellConfig:
    """Paper I's cell: the robot, no person, the three calibration cameras, anti-aliased
    renders (2×2 samples per pixel)."""
    config = CellConfig(seed=seed, cameras=calibration_cameras(), camera_scale=camera_scale, supersample=2, renderer="pybullet")
    config.person = replace(config.person, enabled=False)
    return config


def calibration_cell(
    config: CellConfig,
    *,
    pose_error: tuple[float, float] = (0.05, 5.0),
    mount_error: tuple[float, float] = (0.004, 1.0),
    seed: int = 0,
):
    """The cell with the board attached. Each fixed camera is moved `pose_error` (m,
    degrees) away from where the configuration puts it, and the board is `mount_error`
    off its designed mount (`nominal_mount`); returns (cell, true flange_from_board)."""
    from earcore.sim.cell import SimulatedCell

    rng = np.random.default_rng([seed, 61])
    cell = SimulatedCell(config)
    for cam in cell.cameras:
        if cam.mount is None and (pose_error[0] > 0 or pose_error[1] > 0):
            cam.place(perturb_pose(cam.base_from_camera, pose_error[0], np.radians(pose_error[1]), rng))
    mount = perturb_pose(nominal_mount(), mount_error[0], np.radians(mount_error[1]), rng)
    cell.attach_tool(Checkerboard(), mount)
    return cell, mount


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) of the rotation between two poses."""
    return rotation_spread_deg(np.stack([a, b]))


@dataclass
class CalibrationErrors:
    camera: str
    #: base_from_camera: translation error along the camera's own x, y, z (m; z is the
    #: viewing direction) and its length, rotation error (degrees).
    translation_xyz: tuple[float, float, float]
    translation: float
    rotation_deg: float
    #: Lenses: largest pixel displacement against the true lens at the corners seen
    #: (or over the region they span when no corners are given).
    depth_lens_px: float
    colour_lens_px: float
    #: depth_from_colour: translation (m) and rotation (degrees) errors.
    offset_translation: float
    offset_rotation_deg: float
    mount_translation: float
    #: The depth error left after the calibrated correction (m), RMS and largest over
    #: the corners seen (NaN without observations).
    depth_error_rms: float = float("nan")
    depth_error_max: float = float("nan")


def evaluate(cell, calibration: CameraCalibration, true_mount: np.ndarray | None = None, observations=None) -> CalibrationErrors:
    """Errors of a camera's calibration against the simulation's truth; with the
    calibration's `observations`, the lenses are compared at the corners they saw."""
    cam = next(c for c in cell.cameras if c.name == calibration.name)
    truth = cam.base_from_camera
    est = calibration.base_from_camera
    local = truth[:3, :3].T @ (est[:3, 3] - truth[:3, 3])
    sensor = cam.sensor
    ir_px = colour_px_seen = None
    if observations:
        ir_px = np.concatenate([o.ir.corners for o in observations])
        seen = [o.colour.corners for o in observations if o.colour is not None]
        colour_px_seen = np.concatenate(seen) if seen else None
    depth_px = colour_px = offset_t = offset_r = float("nan")
    if not calibration.has_depth and calibration.colour_K is not None:
        # A colour-only camera: its one lens is the sensor's.
        colour_px = lens_displacement(
            calibration.colour_K, calibration.colour_distortion, sensor.intrinsics, sensor.distortion,
            calibration.colour_size or (sensor.width, sensor.height), region=calibration.colour_region, pixels=ir_px,
        )
    else:
        depth_px = lens_displacement(
            calibration.depth_K, calibration.depth_distortion, sensor.intrinsics, sensor.distortion,
            calibration.depth_size or (sensor.width, sensor.height), region=calibration.depth_region, pixels=ir_px,
        )
    if calibration.has_depth and calibration.colour_K is not None and sensor.colour is not None:
        c = sensor.colour
        colour_px = lens_displacement(
            calibration.colour_K, calibration.colour_distortion, c.intrinsics, c.distortion,
            calibration.colour_size or (c.width, c.height), region=calibration.colour_region, pixels=colour_px_seen,
        )
        if calibration.depth_from_colour is not None:
            offset_t = float(np.linalg.norm(calibration.depth_from_colour[:3, 3] - c.depth_from_colour[:3, 3]))
            offset_r = _angle_deg(calibration.depth_from_colour, c.depth_from_colour)
    depth_rms = depth_max = float("nan")
    if observations and calibration.has_depth and ir_px is not None:
        # The true depths of the corners seen (true pose, true mount) and the image radius.
        camera_from_base = np.linalg.inv(truth)
        board = Checkerboard().inner_corners()
        z = np.concatenate(
            [apply_pose(camera_from_base @ o.base_from_flange @ (true_mount if true_mount is not None else nominal_mount()), board)[:, 2]
             for o in observations]
        )
        rho2 = radius2_of(ir_px, sensor.intrinsics)
        left = sensor.depth_bias.error(z, rho2) - calibration.depth_bias.error(z, rho2)
        depth_rms, depth_max = float(np.sqrt(np.mean(left**2))), float(np.abs(left).max())
    mount_t = float("nan")
    if true_mount is not None and calibration.flange_from_board is not None:
        mount_t = float(np.linalg.norm(calibration.flange_from_board[:3, 3] - true_mount[:3, 3]))
    return CalibrationErrors(
        calibration.name, (float(local[0]), float(local[1]), float(local[2])), float(np.linalg.norm(local)), _angle_deg(est, truth),
        depth_px, colour_px, offset_t, offset_r, mount_t, depth_rms, depth_max,
    )
