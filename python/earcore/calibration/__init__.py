"""Automatic robot-camera calibration (Paper I): a robot-held checkerboard, every fixed
camera's lenses (Zhang's method, refined with the robot as the rig), colour-depth
offset and pose in the robot's base frame (eye-to-hand), in one YAML file the
perception loop reads. Needs OpenCV (`pip install 'earcore[calibration]'`).
"""

from earcore.calibration.board import Checkerboard, Detection, corner_points, detect_board
from earcore.calibration.check import PoseCheck, check_camera
from earcore.calibration.config import CalibrationConfig, full_trajectory, nominal_mount
from earcore.calibration.errors import (
    BoardNotSeen,
    CalibrationError,
    CalibrationFileError,
    DegeneratePoses,
    PoorCalibration,
    TooFewFrames,
)
from earcore.calibration.estimate import Estimator, Observation, SensorSpec
from earcore.calibration.eye_to_hand import EyeToHand, fit_eye_to_hand
from earcore.calibration.intrinsics import LensFit, calibrate_lens, calibrate_lens_on_robot, lens_displacement
from earcore.calibration.motion import BoardMotion
from earcore.calibration.procedure import Calibrator
from earcore.calibration.store import Calibration, CameraCalibration

__all__ = [
    "BoardMotion",
    "BoardNotSeen",
    "Calibration",
    "Checkerboard",
    "CalibrationError",
    "CalibrationFileError",
    "CalibrationConfig",
    "Calibrator",
    "CameraCalibration",
    "DegeneratePoses",
    "Detection",
    "Estimator",
    "EyeToHand",
    "LensFit",
    "Observation",
    "PoorCalibration",
    "PoseCheck",
    "SensorSpec",
    "TooFewFrames",
    "calibrate_lens",
    "calibrate_lens_on_robot",
    "check_camera",
    "corner_points",
    "detect_board",
    "fit_eye_to_hand",
    "full_trajectory",
    "lens_displacement",
    "nominal_mount",
]
