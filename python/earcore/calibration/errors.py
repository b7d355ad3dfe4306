"""Calibration errors: each names the camera and the cause."""

from __future__ import annotations

from earcore.errors import EarcoreError

__all__ = ["BoardNotSeen", "CalibrationError", "CalibrationFileError", "DegeneratePoses", "PoorCalibration", "TooFewFrames"]


class CalibrationError(EarcoreError, RuntimeError):
    """Calibration of one camera failed; `camera` names it."""

    def __init__(self, camera: str, message: str) -> None:
        super().__init__(f"camera {camera!r}: {message}")
        self.camera = camera


class BoardNotSeen(CalibrationError):
    """The camera never detected the board (not in view, too far, occluded)."""

    def __init__(self, camera: str, detail: str = "") -> None:
        super().__init__(camera, "the checkerboard was never detected" + (f" ({detail})" if detail else ""))


class TooFewFrames(CalibrationError):
    def __init__(self, camera: str, got: int, needed: int, detail: str = "") -> None:
        super().__init__(camera, f"{got} usable frames, at least {needed} needed" + (f" ({detail})" if detail else ""))
        self.got, self.needed = got, needed


class DegeneratePoses(CalibrationError):
    """The frames lack the variety (rotation, field-of-view coverage) a quantity needs."""


class PoorCalibration(CalibrationError):
    """The fit succeeded, but its reported uncertainty is beyond the stated quality
    (`CalibrationConfig.max_pose_sigma_m` / `max_pose_sigma_deg`)."""


class CalibrationFileError(EarcoreError, ValueError):
    """The calibration file is missing, not YAML, or lacks what a camera entry needs."""
