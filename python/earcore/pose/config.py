"""`[pose]` of `earcore run`'s configuration: which camera the main job runs the pose
network on, with which weights, how often."""

from __future__ import annotations

from dataclasses import dataclass

from earcore.validate import ConfigError, positive

__all__ = ["PoseConfig"]


@dataclass
class PoseConfig:
    #: The camera (a name from `[cell]`'s cameras) whose colour image the network reads;
    #: empty: the main job runs no pose network.
    camera: str = ""
    #: An exported network (.onnx with its .json beside it); empty: the shipped weights.
    weights: str = ""
    #: Estimates per simulated second (each costs a few milliseconds and one image in the recording).
    rate_hz: float = 2.0

    def validate(self, where: str, cameras: list[str] | None = None) -> PoseConfig:
        if not isinstance(self.camera, str) or not isinstance(self.weights, str):
            raise ConfigError(f"{where}.camera and {where}.weights must be strings")
        if self.camera and cameras is not None and self.camera not in cameras:
            raise ConfigError(f"{where}.camera {self.camera!r} is not one of the cell's cameras: {', '.join(cameras)}")
        positive(self.rate_hz, f"{where}.rate_hz", at_most=100.0)
        return self
