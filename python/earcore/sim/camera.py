"""Cameras: the interface the perception loop reads (frames + intrinsics + pose), and
the simulated RGB-D camera that renders the pybullet cell through a sensor model.

Real cameras or recorded frames plug in by implementing `Camera`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from earcore.sim.sensors import SensorModel

__all__ = ["Camera", "Frame", "SimulatedCamera", "opengl_projection", "opengl_view"]


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


@runtime_checkable
class Camera(Protocol):
    name: str
    sensor: SensorModel

    @property
    def base_from_camera(self) -> np.ndarray: ...

    def capture(self, time: float) -> Frame: ...


def opengl_projection(sensor: SensorModel, near: float = 0.05, far: float = 10.0) -> list[float]:
    """pybullet's (column-major) projection matrix reproducing the pinhole K exactly,
    with OpenCV's pixel convention (pixel (u, v) centred at (u, v), v downward).

    The tiny renderer samples pixel u at window x = u and row v at window y = H - 1 - v
    (measured: tilted planes back-project within 15 µm with these offsets, and half a
    pixel off without them), hence cx and cy + 1 below rather than the textbook + 0.5."""
    w, h = sensor.width, sensor.height
    p = np.zeros((4, 4))
    p[0, 0] = 2 * sensor.fx / w
    p[0, 2] = 1 - 2 * sensor.cx / w
    p[1, 1] = 2 * sensor.fy / h
    p[1, 2] = 2 * (sensor.cy + 1.0) / h - 1
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2 * far * near / (far - near)
    p[3, 2] = -1
    return p.T.reshape(-1).tolist()


def opengl_view(base_from_camera: np.ndarray) -> list[float]:
    """pybullet's view matrix for an OpenCV-convention camera pose (z forward, y down)."""
    gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    world_from_gl = base_from_camera @ gl_from_cv
    return np.linalg.inv(world_from_gl).T.reshape(-1).tolist()


class SimulatedCamera:
    """A camera in the pybullet cell: renders colour, true depth and segmentation with
    the tiny renderer, then applies its sensor's noise model.

    `mount` is None for a fixed camera or a (body id, link index, link_from_camera)
    triple for one carried by the robot (e.g. on the end-effector)."""

    def __init__(
        self,
        client,
        name: str,
        sensor: SensorModel,
        base_from_camera: np.ndarray,
        *,
        rng: np.random.Generator,
        mount: tuple[int, int, np.ndarray] | None = None,
        world_from_base: np.ndarray | None = None,
    ) -> None:
        self.client = client
        self.name = name
        self.sensor = sensor
        self._pose = np.asarray(base_from_camera, dtype=np.float64)
        self.mount = mount
        self.rng = rng
        self.world_from_base = np.eye(4) if world_from_base is None else world_from_base
        self._near, self._far = 0.05, sensor.far + 1.0
        self._projection = opengl_projection(sensor, self._near, self._far)

    @property
    def base_from_camera(self) -> np.ndarray:
        """True pose (ground truth; the perception loop uses calibrated poses)."""
        if self.mount is None:
            return self._pose.copy()
        body, link, link_from_camera = self.mount
        p = self.client
        state = p.getLinkState(body, link, computeForwardKinematics=True)
        world_from_link = np.eye(4)
        world_from_link[:3, :3] = np.reshape(p.getMatrixFromQuaternion(state[5]), (3, 3))
        world_from_link[:3, 3] = state[4]
        return np.linalg.inv(self.world_from_base) @ world_from_link @ link_from_camera

    def render_true(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour (H, W, 3), true metric depth (H, W; 0 where nothing within range) and
        segmentation (H, W; body id, -1 background)."""
        p = self.client
        world_from_camera = self.world_from_base @ self.base_from_camera
        _, _, rgba, depth_buffer, seg = p.getCameraImage(
            self.sensor.width,
            self.sensor.height,
            opengl_view(world_from_camera),
            self._projection,
            renderer=p.ER_TINY_RENDERER,
        )
        h, w = self.sensor.height, self.sensor.width
        rgba = np.reshape(np.asarray(rgba, dtype=np.uint8), (h, w, 4))
        buf = np.reshape(np.asarray(depth_buffer, dtype=np.float64), (h, w))
        n, f = self._near, self._far
        z = f * n / (f - (f - n) * buf)
        z = np.where(buf < 1.0, z, 0.0)
        seg = np.reshape(np.asarray(seg, dtype=np.int64), (h, w))
        body = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)
        return rgba[..., :3].copy(), z, body

    def capture(self, time: float) -> Frame:
        colour, z, body = self.render_true()
        depth = self.sensor.corrupt(z, self.rng)
        return Frame(self.name, time, colour, depth, self.sensor.intrinsics, self.base_from_camera, body)
