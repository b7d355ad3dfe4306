"""The main job's pose network: on one camera's colour image, a few times per simulated
second, estimate the robot's mask, joints and base (`earcore.pose.estimate`), compare
them with the truth (the same keypoints the training images carry) and draw both in the
papers' convention for the recording and a PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from earcore.pose.config import PoseConfig
from earcore.pose.overlay import overlay, project
from earcore.sim.robot_images import keypoint_frames, keypoint_positions

__all__ = ["PoseWatch"]


class PoseWatch:
    def __init__(self, config: PoseConfig, robot: str) -> None:
        from earcore.pose.inference import load_model

        self.config = config
        self.robot = robot
        self.weights = config.weights or None
        model = load_model(self.weights)  # a missing network or onnxruntime fails here, before the run
        known = list(model.sidecar["robots"])
        if robot not in known:
            # Its keypoints would be compared with another robot's: a number with no meaning.
            from earcore.errors import ConfigError

            raise ConfigError(f"pose: the network knows {', '.join(known) or 'no robots'}, not the cell's {robot!r}")
        self.period = 1.0 / config.rate_hz
        self._next = 0.0
        self.joint_errors: list[float] = []
        self.base_errors: list[float] = []
        self.types: list[bool] = []
        self.last: np.ndarray | None = None
        self._frames: tuple[list[int], np.ndarray] | None = None  # read from the URDF once, on the first estimate

    def observe(self, time_s: float, cell, frames) -> np.ndarray | None:
        """The overlay picture of this frame set's estimate, if one is due; None otherwise."""
        from earcore.pose.inference import estimate

        frame = next((f for f in frames if f.camera == self.config.camera), None)
        if frame is None or time_s + 1e-9 < self._next:
            return None
        self._next = time_s + self.period
        result = estimate(frame.colour, frame.K, self.weights)
        camera_from_base = np.linalg.inv(frame.base_from_camera)
        if self._frames is None:
            self._frames = keypoint_frames(cell.model, self.robot)
        truth = keypoint_positions(cell.model, self._frames, cell.q) @ camera_from_base[:3, :3].T + camera_from_base[:3, 3]
        base = (camera_from_base @ cell.model.base)[:3, 3]
        count = min(len(truth), len(result.keypoints))
        self.joint_errors.append(float(np.linalg.norm(result.keypoints[:count] - truth[:count], axis=1).mean()))
        self.base_errors.append(float(np.linalg.norm(result.base - base)))
        self.types.append(result.robot == self.robot)
        self.last = overlay(frame.colour, mask=result.mask, predicted=result.pixels, truth=project(truth, frame.K), base=result.base_pixel)
        return self.last

    def summary(self) -> dict:
        if not self.joint_errors:
            return {"camera": self.config.camera, "estimates": 0}
        return {
            "camera": self.config.camera,
            "estimates": len(self.joint_errors),
            "joints_median_cm": round(100 * float(np.median(self.joint_errors)), 2),
            "base_median_cm": round(100 * float(np.median(self.base_errors)), 2),
            "type_accuracy": round(float(np.mean(self.types)), 3),
        }

    def save_last(self, path: Path) -> Path | None:
        """The last overlay as a PNG (earcore's own writer: no imaging library needed)."""
        if self.last is None:
            return None
        from earcore.learning import png

        png.write(path, self.last)
        return path
