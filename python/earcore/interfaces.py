"""What real hardware implements: a camera that delivers `Frame`s and a robot that
reports its joints and takes velocity commands. The perception loop, the planner and
calibration read only these; the simulated cell (`earcore.sim`) is one implementation,
recorded frames or real drivers are others.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["Camera", "Frame", "RobotInterface"]


@dataclass
class Frame:
    """One RGB-D frame. `depth` in metres (0 = no return); `segmentation` is ground
    truth from the simulator (pybullet body id per pixel, -1 background) and None for
    real cameras."""

    camera: str
    time: float
    colour: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float64
    K: np.ndarray  # (3, 3)
    base_from_camera: np.ndarray  # (4, 4), the pose the frame was taken from (as far as known)
    segmentation: np.ndarray | None = None
    #: Lens distortion of the depth image (OpenCV's k1, k2, p1, p2, k3); None = none.
    distortion: np.ndarray | None = None


@runtime_checkable
class Camera(Protocol):
    """A camera the perception loop can read: its name, its sensor's description
    (resolution, intrinsics, whether it has depth), its pose and its frames."""

    name: str
    sensor: Any

    @property
    def base_from_camera(self) -> np.ndarray: ...

    def capture(self, time: float) -> Frame: ...


@runtime_checkable
class RobotInterface(Protocol):
    """What the perception and planning loops need from a robot, real or simulated."""

    @property
    def joint_positions(self) -> np.ndarray: ...

    @property
    def joint_velocities(self) -> np.ndarray: ...

    def command_velocities(self, qd: np.ndarray) -> None: ...
