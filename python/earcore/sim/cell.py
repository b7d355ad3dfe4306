"""The simulated work cell: a pybullet world (DIRECT, no window) with a table, a robot
on it, static boxes, RGB-D cameras and a person's arm, stepped deterministically.

World frame = the robot's base frame (table top at z = 0). Simulation time is the
cell's own clock (`time_step` per step), independent of how long rendering takes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from earcore.interfaces import Frame
from earcore.robots import RobotModel, load, urdf_path
from earcore.sim.camera import SimulatedCamera
from earcore.sim.config import CellConfig
from earcore.sim.controller import JointTrajectoryController
from earcore.sim.person import HumanArm, Reach
from earcore.sim.raster import CellScene
from earcore.sim.sensors import SENSORS
from earcore.sim.tools import visual_shape
from earcore.transforms import look_at, quaternion
from earcore.urdf import parse_urdf

__all__ = ["SimulatedCell", "default_waypoints"]


#: A-B-A joint targets per built-in robot (arm up in front, then swung to the side).
_WAYPOINTS = {
    "ur5": [[0.0, -1.9, 1.6, -1.3, -1.57, 0.0], [1.3, -1.3, 1.2, -1.5, -1.57, 0.0]],
    "ur3": [[0.0, -1.9, 1.6, -1.3, -1.57, 0.0], [1.3, -1.3, 1.2, -1.5, -1.57, 0.0]],
    "ur10": [[0.0, -1.9, 1.6, -1.3, -1.57, 0.0], [1.3, -1.3, 1.2, -1.5, -1.57, 0.0]],
    "iiwa": [[0.0, 0.6, 0.0, -1.2, 0.0, 0.8, 0.0], [1.2, 0.4, 0.0, -1.4, 0.0, 0.8, 0.0]],
    "panda": [[0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8, 0.02, 0.02], [1.2, -0.1, 0.0, -2.0, 0.0, 2.0, 0.8, 0.02, 0.02]],
}


def default_waypoints(robot: str) -> list[np.ndarray]:
    return [np.array(w, dtype=np.float64) for w in _WAYPOINTS[robot.lower()]]


def _flush_c_stdio() -> None:
    """fflush(NULL): write out the C library's stdio buffers (where it can be reached)."""
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # pragma: no cover - no C library to reach (Windows)
        pass


class _quiet_stdout:
    """Silence C-level writes to stdout (file descriptor 1), and with `stderr` to
    stderr (2) too, for a moment."""

    def __init__(self, stderr: bool = False) -> None:
        self._fds = (1, 2) if stderr else (1,)

    def __enter__(self):
        import os
        import sys

        sys.stdout.flush()
        sys.stderr.flush()
        _flush_c_stdio()
        self._saved = [os.dup(fd) for fd in self._fds]
        devnull = os.open(os.devnull, os.O_WRONLY)
        for fd in self._fds:
            os.dup2(devnull, fd)
        os.close(devnull)

    def __exit__(self, *exc):
        import os

        _flush_c_stdio()  # what C buffered (stdout into a pipe is block-buffered) goes to /dev/null too
        for fd, saved in zip(self._fds, self._saved):
            os.dup2(saved, fd)
            os.close(saved)


def _pybullet():
    """pybullet and its BulletClient, imported without pybullet's "pybullet build time"
    line (printed by its C module on import: on stdout or stderr by build)."""
    try:
        with _quiet_stdout(stderr=True):
            import pybullet
            from pybullet_utils.bullet_client import BulletClient
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("the simulated cell needs pybullet: pip install 'earcore[robots]'") from exc
    return pybullet, BulletClient


class SimulatedCell:
    def __init__(self, config: CellConfig = CellConfig()) -> None:
        if config.robot_meshes not in ("visual", "collision"):
            raise ValueError(f"robot_meshes must be 'visual' or 'collision', got {config.robot_meshes!r}")
        pybullet, BulletClient = _pybullet()
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        with _quiet_stdout():  # pybullet prints "argv[0]=" on connect
            self.p = p = BulletClient(pybullet.DIRECT)
        self.time = 0.0
        self._static_bodies = self._build_static(config)
        # The robot, in pybullet and as earcore's model (same URDF, same root frame).
        path = urdf_path(config.robot)
        self.robot_id = self._load_robot(path, config.robot_meshes)
        self.model: RobotModel = load(config.robot, padding=config.padding)
        self.model.base = self._root_frame()
        joints = [p.getJointInfo(self.robot_id, j) for j in range(p.getNumJoints(self.robot_id))]
        index = {j[1].decode(): j[0] for j in joints}
        self.joint_ids = [index[name] for name in self.model.joint_names]
        self.link_ids = {j[12].decode(): j[0] for j in joints}
        urdf = {j.name: j for j in parse_urdf(path).joints}
        velocity = np.array([urdf[n].velocity for n in self.model.joint_names])
        velocity = np.where(np.isfinite(velocity), velocity, 1.0)
        self.controller = JointTrajectoryController(
            config.speed_fraction * velocity,
            np.full(self.model.dof, config.acceleration_fraction * config.max_acceleration),
        )
        self.q = default_waypoints(config.robot)[0].copy()
        self._qd = np.zeros_like(self.q)
        self._commanded: np.ndarray | None = None
        self._apply_joints()
        #: The world as the core's rasterizer draws it (renderer "raster"), shared by the cameras.
        self.scene = CellScene(p) if config.renderer == "raster" and config.cameras else None
        self.cameras = [self._make_camera(c) for c in config.cameras]
        self._next_capture = {c.name: 0.0 for c in self.cameras}
        self.person = self._make_person(config) if config.person.enabled else None
        #: Tools held by the robot: (pybullet body, flange_from_tool, tool).
        self.tools: list[tuple[int, np.ndarray, object]] = []

    # --- building -------------------------------------------------------------

    def _build_static(self, config: CellConfig) -> list[int]:
        p = self.p
        bodies = []

        def box(lo, hi, colour):
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            half = (hi - lo) / 2
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half.tolist())
            visual = p.createVisualShape(p.GEOM_BOX, halfExtents=half.tolist(), rgbaColor=colour)
            bodies.append(p.createMultiBody(0, shape, visual, ((lo + hi) / 2).tolist()))

        sx, sy = config.table_size
        h = config.table_height
        box(*self.table_box(), (0.55, 0.45, 0.35, 1))  # table top
        for x in (-0.3, -0.4 + sx):
            for y in (-sy / 2 + 0.05, sy / 2 - 0.05):
                box([x, y - 0.03, -h], [x + 0.06, y + 0.03, -0.04], (0.4, 0.4, 0.4, 1))  # legs
        box([-2.5, -2.5, -h - 0.02], [2.5, 2.5, -h], (0.75, 0.75, 0.72, 1))  # floor
        for b in config.boxes:
            box(b[:3], b[3:], (0.2, 0.45, 0.7, 1))
        return bodies

    def _load_robot(self, path, meshes: str) -> int:
        if meshes == "visual":
            return self.p.loadURDF(str(path), useFixedBase=True)
        import tempfile

        from earcore.urdf import collision_as_visual

        # pybullet reads the meshes while loading: the rewritten URDF can go after.
        with tempfile.TemporaryDirectory(prefix="earcore-robot-") as folder:
            return self.p.loadURDF(str(collision_as_visual(path, folder)), useFixedBase=True)

    def table_box(self) -> tuple[list[float], list[float]]:
        """The table top's box (min, max corners) in the base frame; its top is z = 0."""
        sx, sy = self.config.table_size
        return [-0.35, -sy / 2, -0.04], [-0.35 + sx, sy / 2, 0.0]

    def _root_frame(self) -> np.ndarray:
        """world_from_root of the loaded robot (pybullet reports the inertial frame)."""
        p = self.p
        pos, orn = p.getBasePositionAndOrientation(self.robot_id)
        info = p.getDynamicsInfo(self.robot_id, -1)
        pos, orn = p.multiplyTransforms(pos, orn, *p.invertTransform(info[3], info[4]))
        m = np.eye(4)
        m[:3, :3] = np.reshape(p.getMatrixFromQuaternion(orn), (3, 3))
        m[:3, 3] = pos
        return m

    def _tool_link(self) -> int:
        names = self.model.link_names
        for candidate in ("tool0", "panda_grasptarget", "panda_hand", "lbr_iiwa_link_7"):
            if candidate in self.link_ids:
                return self.link_ids[candidate]
        return self.link_ids[names[-1]]

    def _make_camera(self, c) -> SimulatedCamera:
        if c.sensor not in SENSORS:
            raise ValueError(f"camera {c.name!r}: unknown sensor {c.sensor!r}; known: {sorted(SENSORS)}")
        sensor = SENSORS[c.sensor]
        if self.config.camera_scale != 1.0:
            sensor = sensor.scaled(self.config.camera_scale)
        if sensor.colour is not None and self.config.colour_scale != 1.0:
            sensor = replace(sensor, colour=sensor.colour.scaled(self.config.colour_scale))
        rng = np.random.default_rng([self.config.seed, len(c.name), sum(map(ord, c.name))])
        if c.mount == "world":
            return SimulatedCamera(
                self.p, c.name, sensor, look_at(c.position, c.target), rng=rng, supersample=self.config.supersample, scene=self.scene
            )
        if c.mount == "end_effector":
            link_from_camera = np.eye(4)
            link_from_camera[:3, 3] = c.position
            return SimulatedCamera(
                self.p,
                c.name,
                sensor,
                np.eye(4),
                rng=rng,
                mount=(self.robot_id, self._tool_link(), link_from_camera),
                supersample=self.config.supersample,
                scene=self.scene,
            )
        raise ValueError(f"camera {c.name!r}: mount must be 'world' or 'end_effector', got {c.mount!r}")

    def _make_person(self, config: CellConfig) -> HumanArm:
        pc = config.person
        if pc.reach_starts:
            if len(pc.reach_starts) != len(pc.reach_targets):
                raise ValueError("person.reach_starts and person.reach_targets must have the same length")
            n = len(pc.reach_starts)
            speeds: list[float | None] = list(pc.reach_speeds) or [None] * n
            holds = list(pc.reach_holds) or [pc.hold_s] * n
            if len(speeds) != n or len(holds) != n:
                raise ValueError("person.reach_speeds and reach_holds must be empty or as long as person.reach_starts")
            reaches = [Reach(s, (float(t[0]), float(t[1]), float(t[2])), h, v, pc.wander) for s, t, h, v in zip(pc.reach_starts, pc.reach_targets, holds, speeds)]
        else:
            starts = np.cumsum(self.rng.uniform(3.0, 8.0, 8))
            targets = self.rng.uniform([0.3, -0.2, 0.1], [0.6, 0.4, 0.45], (8, 3))
            reaches = [Reach(float(s), tuple(t), pc.hold_s, wander=pc.wander) for s, t in zip(starts, targets)]
        return HumanArm(self.p, pc.shoulder, pc.rest_hand, reaches, peak_speed=pc.peak_speed, arrive=pc.arrive_s)

    def attach_tool(self, tool, flange_from_tool: np.ndarray) -> int:
        """Mount a tool (`earcore.sim.tools.Checkerboard`, `ObstaclePlate`) rigidly on the
        flange (the tool link) at `flange_from_tool`; returns its pybullet body."""
        shape, texture = visual_shape(tool, self.p)
        if texture >= 0 and self.scene is not None:
            raise ValueError(f"{type(tool).__name__} is textured and the cell's renderer is 'raster', which draws no textures: use renderer='pybullet'")
        body = self.p.createMultiBody(0, -1, shape, [0, 0, -10])
        if texture >= 0:
            self.p.changeVisualShape(body, -1, textureUniqueId=texture)
        self.tools.append((body, np.asarray(flange_from_tool, dtype=np.float64), tool))
        self._place_tools()
        return body

    def world_from_flange(self) -> np.ndarray:
        state = self.p.getLinkState(self.robot_id, self._tool_link(), computeForwardKinematics=True)
        m = np.eye(4)
        m[:3, :3] = np.reshape(self.p.getMatrixFromQuaternion(state[5]), (3, 3))
        m[:3, 3] = state[4]
        return m

    def world_from_tool(self, index: int = 0) -> np.ndarray:
        return self.world_from_flange() @ self.tools[index][1]

    def _place_tools(self) -> None:
        for i, (body, _, _) in enumerate(self.tools):
            pose = self.world_from_tool(i)
            x, y, z, w = quaternion(pose[:3, :3])
            self.p.resetBasePositionAndOrientation(body, pose[:3, 3].tolist(), [x, y, z, w])

    # --- the robot interface (what a real driver would provide) ----------------

    @property
    def joint_positions(self) -> np.ndarray:
        return self.q.copy()

    @property
    def joint_velocities(self) -> np.ndarray:
        return self._qd.copy()

    def command_velocities(self, qd: np.ndarray) -> None:
        """Direct velocity command for the next step (bypasses the trajectory follower)."""
        self._commanded = np.asarray(qd, dtype=np.float64)

    # --- running --------------------------------------------------------------

    def _apply_joints(self) -> None:
        for j, v in zip(self.joint_ids, self.q):
            self.p.resetJointState(self.robot_id, j, float(v))

    def step(self) -> None:
        """Advance one time step: the controller (or a direct velocity command) moves
        the robot, its tools follow, the person moves."""
        dt = self.config.time_step
        if self._commanded is not None:
            qd, self._commanded = self._commanded, None
        else:
            qd = self.controller.step(self.q, dt)
        limits = self.model.joint_limits
        self.q = np.clip(self.q + qd * dt, limits[:, 0], limits[:, 1])
        self._qd = qd
        self._apply_joints()
        self._place_tools()
        self.time += dt
        if self.person is not None:
            self.person.set_time(self.time)

    def capture(self, before: float | None = None) -> list[Frame]:
        """Frames of the cameras due at the current time (each at its own rate). With
        `before` (when the frames are next read), a camera whose next frame falls due
        by then is not rendered now, unless the read is now: its frame would be
        replaced unread (a 30 Hz camera feeding a 15 Hz map)."""
        frames = []
        for cam, conf in zip(self.cameras, self.config.cameras):
            if self.time + 1e-9 >= self._next_capture[cam.name]:
                self._next_capture[cam.name] += 1.0 / conf.rate_hz
                if before is not None and self.time + 1e-9 < before and self._next_capture[cam.name] <= before + 1e-9:
                    continue
                frames.append(cam.capture(self.time))
        return frames

    # --- ground truth ---------------------------------------------------------

    def person_segments(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        if self.person is None or not self.person.present(self.time):
            return []
        return self.person.segments(self.time)

    def robot_person_distance(self) -> float:
        """Closest distance between the robot's links and the person's arm (m)."""
        if self.person is None or not self.person.present(self.time):
            return float("inf")
        best = float("inf")
        for body in self.person.bodies:
            for c in self.p.getClosestPoints(self.robot_id, body, 5.0):
                best = min(best, c[8])
        return best

    def close(self) -> None:
        self.p.disconnect()
