"""Has a camera moved since it was calibrated? The robot shows the board where the
camera saw it best; the corners the camera measures (depth, through its calibrated
lens; for a colour-only camera, the board's pose from its image) are compared with where
the calibration says they are."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.calibration.eye_to_hand import apply_pose
from earcore.calibration.procedure import Calibrator
from earcore.calibration.store import CameraCalibration

__all__ = ["PoseCheck", "check_camera"]


@dataclass
class PoseCheck:
    camera: str
    seen: bool
    #: Mean distance (m) between measured and predicted corners (NaN when not seen).
    residual: float
    moved: bool

    def __str__(self) -> str:
        if not self.seen:
            return f"{self.camera}: MOVED? the board is not seen where the calibration expects it"
        verdict = "MOVED: recalibrate it" if self.moved else "ok"
        return f"{self.camera}: corners {1000 * self.residual:.1f} mm from where the calibration puts them: {verdict}"


def check_camera(calibrator: Calibrator, calibration: CameraCalibration, *, threshold: float = 0.01) -> PoseCheck:
    """Move to the camera's start pose, capture, compare (`threshold` in metres)."""
    name = calibration.name
    if calibration.start_q is None or calibration.flange_from_board is None:
        raise ValueError(f"camera {name!r}: the calibration has no start pose or board mount to check against")
    q = np.asarray(calibration.start_q, dtype=np.float64)
    if not calibrator.motion.go_to(q):
        raise RuntimeError(f"camera {name!r}: its start pose cannot be reached from here")
    obs = calibrator.observe(name, colour=False)
    if obs is None:
        return PoseCheck(name, False, float("nan"), True)
    # The image the board was found in: the depth camera's, or a colour-only camera's own.
    calibration.check_image_size(*obs.ir.image_size, colour=calibration.depth_K is None)
    if calibration.depth_K is not None:
        measured = calibrator.estimator.corners_3d(obs, calibration.depth_K, calibration.depth_distortion, calibration.depth_bias)
    elif calibration.colour_K is not None:  # a colour-only camera: where the board's pose from its image puts them
        pose = calibrator.estimator.board_poses([obs], calibration.colour_K, calibration.colour_distortion)[0]
        measured = apply_pose(pose, calibrator.board_points)
    else:
        raise ValueError(f"camera {name!r}: the calibration has no lens to measure the board with")
    camera_from_board = np.linalg.inv(calibration.base_from_camera) @ obs.base_from_flange @ calibration.flange_from_board
    predicted = apply_pose(camera_from_board, calibrator.board_points)
    ok = np.isfinite(measured).all(axis=1)
    residual = float(np.linalg.norm(measured[ok] - predicted[ok], axis=1).mean()) if ok.any() else float("nan")
    return PoseCheck(name, True, residual, not (residual <= threshold))
