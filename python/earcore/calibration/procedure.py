"""Paper I's Algorithm 1 in the cell: the robot carries the checkerboard through each
camera's view, and every camera gets its lenses, its colour-depth offset and its pose
in the robot's base frame.

Per camera, after one 360° sweep that every camera watches:
  start pose (where the camera saw the board nearest its image centre) → initial
  eye-to-hand → tilt limits (roll, pitch, yaw in steps both ways until detection fails)
  → the board's mount from tilting in place → staged positions outward from the image
  centre, re-aimed after every accepted frame with the refined eye-to-hand, then again
  20 % farther → Zhang's method for the IR/depth and colour lenses and their offset →
  the depth error (depth distortion) → eye-to-hand again with the corrected lenses and
  depths.

The robot side is forward kinematics of the joint state at capture; every motion is
checked against a map of the cell's known geometry and unreachable or colliding poses
are skipped. Simulated robot time is counted (`motion_time`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

import earcore
from earcore.calibration.board import Detection, _cv2, corner_points, detect_board
from earcore.calibration.errors import BoardNotSeen, CalibrationError, DegeneratePoses, TooFewFrames
from earcore.calibration.eye_to_hand import (
    EyeToHand,
    apply_pose,
    fit_eye_to_hand,
    fit_eye_to_hand_from_poses,
    mean_pose,
    refine_by_reprojection,
)
from earcore.calibration.intrinsics import calibrate_lens, calibrate_lens_on_robot, reprojection_errors
from earcore.calibration.store import Calibration, CalibrationFileError, CameraCalibration
from earcore.cloud import box_voxel_centres
from earcore.depth_error import DepthBias, radius2_grid, radius2_of
from earcore.planning.errors import PlanningError
from earcore.planning.ik import UnreachablePose, rotation_vector, solve_ik
from earcore.planning.rrt import JointSpacePlanner
from earcore.sim.tools import Checkerboard

__all__ = ["CalibrationSettings", "Calibrator", "Observation", "full_trajectory", "nominal_mount"]


def nominal_mount(extension: float = 0.10) -> np.ndarray:
    """flange_from_board as designed: the board's centre `extension` metres out along the
    flange's z axis, its printed face (z) facing the same way."""
    m = np.eye(4)
    m[2, 3] = extension
    return m


def _region(detections: list[Detection]) -> tuple[int, int, int, int]:
    """(u_min, v_min, u_max, v_max) of the corners of all detections."""
    px = np.concatenate([d.corners for d in detections])
    lo, hi = np.floor(px.min(axis=0)).astype(int), np.ceil(px.max(axis=0)).astype(int)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    m = np.eye(4)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


@dataclass
class CalibrationSettings:
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
    #: by pixels and the pose by millimetres (NOTES.md).
    lens_model: str = "radial"
    #: A calibration whose corners reproject worse than this (pixels rms) is refused.
    max_reprojection_px: float = 1.0
    #: Passes of lens-and-pose from pixels / mount from depth in step 7.
    refinement_passes: int = 4
    #: The depth error's terms to fit (of offset + scale·z + radial·ρ²·z²,
    #: `earcore.depth_error`) from the corners' measured depth against where the robot
    #: and the pose from the pixels put them (Paper I's depth distortion), taken out
    #: before the final 3D-3D fit; () fits none.
    depth_error_terms: tuple[str, ...] = ("offset", "scale", "radial")
    seed: int = 0


def full_trajectory(settings: CalibrationSettings) -> CalibrationSettings:
    """The dense staged trajectory (more stages, more positions per stage: overlapping
    views, like Paper I's long runs) and no frame limit; the default trajectory is the
    sparse one that covers the field of view in ~30 frames."""
    return replace(settings, stage_radii=(0.0, 0.3, 0.55, 0.8), stage_positions=(1, 6, 8, 12), max_frames=None)


@dataclass
class Observation:
    """One accepted frame of one camera."""

    camera: str
    q: np.ndarray
    base_from_flange: np.ndarray
    ir: Detection
    colour: Detection | None
    #: Depth frames (F, h, w) of the image region around the board, from pixel `origin`.
    depth: np.ndarray
    origin: tuple[int, int]
    tilted: bool
    #: Where in Algorithm 1: "start", "tilt" (a tilt limit) or "stage" (the trajectory).
    phase: str = "stage"
    #: For stage frames: the distance factor and the stage's radius (fraction of the
    #: usable half-field of view).
    distance_factor: float | None = None
    radius: float | None = None
    #: For stage frames: the position's index on its stage's ring.
    slot: int | None = None


class _TiltSearch:
    """Watches one camera while the board tilts about one of its axes: at every `step`
    degrees of tilt in the searched direction (the board's rotation since the start,
    as a rotation vector, along that axis) the camera looks; the first miss stops the
    motion. Tilt the other way (on the way over from the previous search) is ignored."""

    def __init__(
        self, calibrator: Calibrator, camera: str, start_flange: np.ndarray, mount: np.ndarray, axis: int, sign: int, step: float
    ) -> None:
        self.calibrator, self.camera, self.step = calibrator, camera, step
        self.start, self.mount = start_flange[:3, :3], mount[:3, :3]
        self.axis, self.sign = axis, sign
        self.next = step
        #: True once the camera lost the board (the motion was stopped).
        self.stopped = False
        #: The largest tilt (degrees) at which the board was still seen, and where.
        self.angle = 0.0
        self.q: np.ndarray | None = None

    def tilt(self, q: np.ndarray) -> float:
        """Signed tilt (degrees) of the board about the searched axis since the start."""
        turn = self.start.T @ self.calibrator.base_from_flange(q)[:3, :3]
        return math.degrees(rotation_vector(self.mount.T @ turn @ self.mount)[self.axis]) * self.sign

    def watch(self, q: np.ndarray) -> bool:
        angle = self.tilt(q)
        if angle + 1e-6 < self.next:
            return True
        self.next = (math.floor(angle / self.step) + 1) * self.step
        if self.calibrator.detect(self.camera) is None:
            self.stopped = True
            return False  # the first failure: stop here
        self.angle, self.q = angle, q.copy()
        return True


class Calibrator:
    """Runs Algorithm 1 on a `SimulatedCell` (or anything with its robot and camera
    interface) holding the checkerboard."""

    def __init__(
        self,
        cell,
        settings: CalibrationSettings | None = None,
        *,
        board: Checkerboard = Checkerboard(),
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.cell = cell
        self.settings = settings or CalibrationSettings()
        self.board = board
        self.board_points = board.inner_corners()
        self.model = cell.model
        self.flange_link = self.model.link_names.index(self._flange_name())
        self.progress = progress or (lambda message: None)
        self.rng = np.random.default_rng(self.settings.seed)
        #: Simulated seconds the robot spent moving.
        self.motion_time = 0.0
        #: Seconds spent in the solvers (lens and eye-to-hand fits).
        self.solver_time = 0.0
        self.observations: dict[str, list[Observation]] = {}
        self.start_poses: dict[str, tuple[float, np.ndarray]] = {}
        self.tilt_limits: dict[str, dict[str, float]] = {}
        self.tree = self._known_geometry()
        self._planner: JointSpacePlanner | None = None
        #: The sweep's "L" pose: open space to pass through between cameras.
        self._home: np.ndarray | None = None

    # --- set-up ---------------------------------------------------------------

    def _flange_name(self) -> str:
        for name in ("tool0", "panda_grasptarget", "panda_hand", "lbr_iiwa_link_7"):
            if name in self.model.link_names:
                return name
        return self.model.link_names[-1]

    def _known_geometry(self):
        """The cell's table and boxes as an occupancy map for motion checks."""
        tree = earcore.OcTree(0.05)
        lo, hi = self.cell.table_box()
        boxes = [(lo, hi)] + [(b[:3], b[3:]) for b in self.cell.config.boxes]
        base = self.model.base[:3, 3]
        for lo, hi in boxes:
            centres = box_voxel_centres(lo, hi, tree.resolution)
            centres = centres[np.linalg.norm(centres[:, :2] - base[:2], axis=1) > 0.25]  # the robot's mount
            if len(centres):
                tree.update_nodes(centres, occupied=True)
        return tree

    def camera(self, name: str):
        for cam in self.cell.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r}; cameras: {[c.name for c in self.cell.cameras]}")

    # --- robot ----------------------------------------------------------------

    def base_from_flange(self, q: np.ndarray) -> np.ndarray:
        return self.model.fk(q)[self.flange_link]

    def go_to(self, q: np.ndarray) -> bool:
        """`move_to` with more planning time, or by way of the sweep's open "L" pose when
        no path is found from here (e.g. from deep in the previous camera's trajectory)."""
        if self.move_to(q, plan_time=3.0):
            return True
        return self._home is not None and self.move_to(self._home, plan_time=3.0) and self.move_to(q, plan_time=3.0)

    def nearest_equivalent(self, q: np.ndarray) -> np.ndarray:
        """`q` with each revolute joint turned by whole turns (where its limits allow) to
        lie closest to the current state: the same pose, reached with the least motion
        (a UR's joints span ±2π, and IK or a 360° sweep may land a turn away)."""
        q = np.asarray(q, dtype=np.float64).copy()
        now = self.cell.joint_positions
        lo, hi = self.model.joint_limits[:, 0], self.model.joint_limits[:, 1]
        for j in range(len(q)):
            if hi[j] - lo[j] <= 2 * math.pi:
                continue
            turns = np.round((now[j] - q[j]) / (2 * math.pi))
            for k in (turns, turns - 1, turns + 1):
                c = q[j] + 2 * math.pi * k
                if lo[j] <= c <= hi[j] and abs(c - now[j]) < abs(q[j] - now[j]):
                    q[j] = c
        return q

    def _path_to(self, q: np.ndarray, plan_time: float | None = None) -> list[np.ndarray] | None:
        """Waypoints from the current state to `q`: the straight motion when it is free,
        else an RRT-Connect path (OMPL, against the cell's known geometry) cut short
        wherever a straight motion skips waypoints; None when there is none."""
        now = self.cell.joint_positions
        if not self.model.check_motion(self.tree, now, q, 0.02):
            return [q]
        if self._planner is None:
            self._planner = JointSpacePlanner(self.model, self.tree, seed=self.settings.seed)
        try:
            limit = self.settings.plan_time if plan_time is None else plan_time
            path = self._planner.plan(now, q, time_limit=limit, simplify=False)[0].waypoints
        except PlanningError:
            return None
        out, i = [], 0
        while i < len(path) - 1:
            j = len(path) - 1
            while j > i + 1 and self.model.check_motion(self.tree, path[i], path[j], 0.02):
                j -= 1
            out.append(path[j])
            i = j
        return out

    def move_to(self, q: np.ndarray, plan_time: float | None = None) -> bool:
        """Drive the robot to `q` (or the same pose a whole turn nearer, per joint), by
        a planned path when the straight motion is blocked; False (and no motion) when
        no path is found."""
        cell = self.cell
        path = None
        # The nearest turn of each joint first; the pose as given when that one has no path.
        for candidate in (self.nearest_equivalent(q), np.asarray(q, dtype=np.float64)):
            path = self._path_to(candidate, plan_time)
            if path is not None:
                break
        if path is None:
            return False
        cell.controller.follow(path)
        steps = 0
        while not cell.controller.done and steps < 3000:
            cell.step()
            steps += 1
        self.motion_time += steps * cell.config.time_step
        return True

    def move_through(self, q: np.ndarray, watch: Callable[[np.ndarray], bool], every: float, *, shortest: bool = True) -> bool:
        """Drive to `q` (when the straight motion is free) calling `watch(q_now)` every
        `every` seconds on the way (cameras capture while the robot moves, their frames
        stamped with the joint state); when it returns False the robot brakes and stops.
        `shortest`: go to the nearest equivalent of `q` (not for a deliberate full turn)."""
        if shortest:
            q = self.nearest_equivalent(q)
        cell = self.cell
        if self.model.check_motion(self.tree, cell.joint_positions, q, 0.02):
            return False
        cell.controller.follow([q])
        steps, next_watch, watching = 0, 0.0, True
        while not cell.controller.done and steps < 6000:
            cell.step()
            steps += 1
            if watching and steps * cell.config.time_step >= next_watch:
                next_watch += every
                if not watch(cell.joint_positions):
                    cell.controller.brake(cell.joint_positions)
                    watching = False
        self.motion_time += steps * cell.config.time_step
        return True

    def flange_targets(self, base_from_board: np.ndarray, mount: np.ndarray, near: np.ndarray | None = None):
        """Collision-free joint states putting the board (as the mount is believed) at
        `base_from_board`: first ones near `near` (default: the current state; short
        motions), then one from anywhere."""
        target = base_from_board @ np.linalg.inv(mount)
        now = self.cell.joint_positions if near is None else np.asarray(near, dtype=np.float64)
        seeds = [now] + [now + self.rng.normal(scale=0.3, size=now.shape) for _ in range(3)] + [None]
        for seed in seeds:
            try:
                yield solve_ik(
                    self.model, target, link=self.flange_link, seed_q=seed, tree=self.tree,
                    position_tolerance=0.02, orientation_tolerance=0.08, restarts=1 if seed is not None else 6,
                    iterations=150, rng=self.rng,
                ).q
            except UnreachablePose:
                continue

    def flange_target(self, base_from_board: np.ndarray, mount: np.ndarray, near: np.ndarray | None = None) -> np.ndarray | None:
        """The first of `flange_targets`, or None when the pose cannot be reached."""
        return next(self.flange_targets(base_from_board, mount, near), None)

    def reach_board_pose(self, base_from_board: np.ndarray, mount: np.ndarray) -> bool:
        """Move so the board (as the mount is believed) sits at `base_from_board`, by the
        first joint state whose straight motion from here is free."""
        for i, q in enumerate(self.flange_targets(base_from_board, mount)):
            if i >= 3:
                break
            if self.move_to(q):
                return True
        return False

    # --- seeing ---------------------------------------------------------------

    def detect(self, name: str) -> Detection | None:
        """The board in camera `name`'s IR image now (no depth: for searches in motion)."""
        return detect_board(self.camera(name).render_true()[0], self.board)

    def has_depth(self, name: str) -> bool:
        return self.camera(name).sensor.has_depth

    def observe(self, name: str, *, tilted: bool = False, colour: bool = True) -> Observation | None:
        """Capture camera `name` with the robot still: detect the board in the IR image
        (and the colour image), keep `depth_frames` depth frames of the board's region
        (none for a colour-only camera, whose own image stands in for the IR image)."""
        cam = self.camera(name)
        image, true_depth, _ = cam.render_true()
        ir = detect_board(image, self.board)
        if ir is None:
            return None
        if not cam.sensor.has_depth:
            q = self.cell.joint_positions
            return Observation(name, q, self.base_from_flange(q), ir, None, np.zeros((0, 0, 0), np.float32), (0, 0), tilted)
        lo = np.maximum(np.floor(ir.corners.min(axis=0)).astype(int) - 40, 0)
        hi = np.ceil(ir.corners.max(axis=0)).astype(int) + 40
        # The board and robot are still: frames differ by the sensor's noise only.
        region = true_depth[lo[1] : hi[1], lo[0] : hi[0]]
        origin = (int(lo[0]), int(lo[1]))
        depth = np.stack([cam.sensor.corrupt(region, cam.rng, origin) for _ in range(self.settings.depth_frames)]).astype(np.float32)
        col = detect_board(cam.render_colour(), self.board) if (colour and cam.sensor.colour is not None) else None
        q = self.cell.joint_positions
        return Observation(name, q, self.base_from_flange(q), ir, col, depth, origin, tilted)

    def corners_3d(self, obs: Observation, K: np.ndarray, distortion, depth_error: DepthBias | None = None) -> np.ndarray:
        """The frame's corners in the camera frame from its depth, through the lens (K,
        distortion), with `depth_error` taken out of the depth first."""
        depth = obs.depth
        if depth_error is not None and not depth_error.is_zero:
            depth = depth_error.correct(depth, radius2_grid(K, depth.shape[2], depth.shape[1], obs.origin))
        return corner_points(obs.ir, depth, K, distortion, method=self.settings.corner_method, origin=obs.origin)

    def depth_error(self, obs: list[Observation], K, distortion, base_from_camera: np.ndarray, mount: np.ndarray) -> DepthBias:
        """Step 7's depth distortion: every corner's measured depth against its depth
        where forward kinematics, the mount and the pose from the pixels put it."""
        measured, predicted, rho2 = [], [], []
        camera_from_base = np.linalg.inv(base_from_camera)
        for o in obs:
            measured.append(self.corners_3d(o, K, distortion)[:, 2])
            predicted.append(apply_pose(camera_from_base @ o.base_from_flange @ mount, self.board_points)[:, 2])
            rho2.append(radius2_of(o.ir.corners, K))
        return DepthBias.fit(
            np.concatenate(measured), np.concatenate(predicted), np.concatenate(rho2), terms=self.settings.depth_error_terms
        )

    # --- Algorithm 1 -----------------------------------------------------------

    def sweep(self, names: list[str]) -> None:
        """Step 1: the board on an upside-down "L" turns 360° about the base while every
        camera watches; each keeps the joint state where it saw the board nearest its
        image centre."""
        s = self.settings
        for elevation in s.sweep_elevations_deg:
            if all(n in self.start_poses for n in names):
                break
            e = math.radians(elevation)
            # Board at angle 0 in front of the base (+x), face outward and up.
            z = np.array([math.cos(e), 0.0, math.sin(e)])
            x = np.array([0.0, 1.0, 0.0])
            board_pose = np.eye(4)
            board_pose[:3, 0], board_pose[:3, 1], board_pose[:3, 2] = x, np.cross(z, x), z
            board_pose[:3, 3] = [s.sweep_radius, 0.0, s.sweep_height]
            if not self.reach_board_pose(self.model.base @ board_pose, s.mount):
                raise CalibrationError("all", f"the sweep pose (elevation {elevation}°) is unreachable")
            q0 = self.cell.joint_positions
            self._home = q0.copy()
            lo, hi = self.model.joint_limits[0]
            # One continuous turn, the way the base joint's limits allow.
            turn = min(2 * math.pi, hi - q0[0]) if hi - q0[0] >= q0[0] - lo else -min(2 * math.pi, q0[0] - lo)
            q1 = q0.copy()
            q1[0] += turn
            self.progress(f"sweep at {elevation:.0f}° elevation: turning {math.degrees(abs(turn)):.0f}° about the base")
            before = self.motion_time

            def watch(q: np.ndarray) -> bool:
                for name in names:
                    detection = self.detect(name)
                    if detection is None:
                        continue
                    score = detection.distance_from_image_centre()
                    if name not in self.start_poses or score < self.start_poses[name][0]:
                        self.start_poses[name] = (score, q.copy())
                return True

            self.move_through(q1, watch, s.watch_period, shortest=False)
            self.progress(f"sweep done: {self.motion_time - before:.0f} s of motion; seen by {sorted(self.start_poses)}")
        for name in names:
            if name not in self.start_poses:
                raise BoardNotSeen(name, f"not during the 360° sweep at elevations {list(s.sweep_elevations_deg)}°")

    def _fit(
        self, name: str, K, distortion, mount: np.ndarray, estimate_mount: bool, obs=None, threshold=None, depth_error=None
    ) -> EyeToHand:
        obs = self.observations[name] if obs is None else obs
        if not self.has_depth(name):
            return self._fit_from_pixels(name, K, distortion, mount, estimate_mount, obs)
        t = time.perf_counter()
        try:
            return fit_eye_to_hand(
                [self.corners_3d(o, K, distortion, depth_error) for o in obs],
                np.array([o.base_from_flange for o in obs]),
                self.board_points,
                mount,
                estimate_mount=estimate_mount,
                threshold=self.settings.ransac_threshold if threshold is None else threshold,
                camera=name,
            )
        finally:
            self.solver_time += time.perf_counter() - t

    def board_poses(self, obs: list[Observation], K, distortion) -> np.ndarray:
        """camera_from_board (F, 4, 4) of every frame from its corners' pixels (PnP for a
        planar target, through the lens K, distortion)."""
        cv2 = _cv2()
        out = np.empty((len(obs), 4, 4))
        for i, o in enumerate(obs):
            ok, rvec, tvec = cv2.solvePnP(
                self.board_points, o.ir.corners.astype(np.float64), np.asarray(K, float), np.asarray(distortion, float),
                flags=cv2.SOLVEPNP_IPPE,
            )
            if not ok:
                raise DegeneratePoses(o.camera, "PnP found no board pose for a frame")
            out[i] = np.eye(4)
            out[i, :3, :3] = cv2.Rodrigues(rvec)[0]
            out[i, :3, 3] = np.ravel(tvec)
        return out

    def _fit_from_pixels(self, name: str, K, distortion, mount: np.ndarray, estimate_mount: bool, obs) -> EyeToHand:
        """Eye-to-hand of a colour-only camera from the board's pose in each frame: AX = ZB
        (OpenCV's robot-world/hand-eye) when the mount is wanted, else the camera pose
        that carries the designed mount's board onto each frame's, averaged."""
        t = time.perf_counter()
        try:
            poses = self.board_poses(obs, K, distortion)
            flanges = np.array([o.base_from_flange for o in obs])
            if estimate_mount:
                return fit_eye_to_hand_from_poses(poses, flanges, self.board_points, camera=name)
            x = mean_pose(np.array([f @ mount @ np.linalg.inv(a) for f, a in zip(flanges, poses)]))
            seen = np.concatenate([apply_pose(x @ a, self.board_points) for a in poses])
            robot = np.concatenate([apply_pose(f @ mount, self.board_points) for f in flanges])
            rmse = float(np.sqrt(np.mean(np.sum((seen - robot) ** 2, axis=1))))
            return EyeToHand(x, np.asarray(mount, dtype=np.float64), rmse, len(obs), len(seen))
        finally:
            self.solver_time += time.perf_counter() - t

    def _board_in_camera(self, fit: EyeToHand, obs: Observation) -> np.ndarray:
        return np.linalg.inv(fit.base_from_camera) @ obs.base_from_flange @ fit.flange_from_board

    def _accept(self, obs: Observation | None) -> bool:
        if obs is None:
            return False
        self.observations[obs.camera].append(obs)
        return True

    def _full(self, name: str) -> bool:
        m = self.settings.max_frames
        return m is not None and len(self.observations[name]) >= m

    def calibrate_camera(self, name: str) -> CameraCalibration:
        s = self.settings
        cam = self.camera(name)
        K0, d0 = cam.sensor.intrinsics, np.zeros(5)  # the datasheet's pinhole, no lens model yet
        if name not in self.start_poses:
            self.sweep([name])
        self.observations[name] = []
        motion_before = self.motion_time
        # Steps 1-2: the start pose and a first eye-to-hand with the mount as designed.
        if not self.go_to(self.start_poses[name][1]):
            raise CalibrationError(name, "the start pose cannot be reached")
        first = self.observe(name)
        if first is None:
            raise BoardNotSeen(name, "at its start pose")
        first.phase = "start"
        self._accept(first)
        loose = s.ransac_threshold_uncorrected
        fit = self._fit(name, K0, d0, s.mount, estimate_mount=False, threshold=loose)
        start_board = fit.base_from_camera @ self._board_in_camera(fit, self.observations[name][0])
        # Step 3: tilt limits, both ways about each board axis. The frame at each limit
        # is kept: those tilted-in-place frames fix the mount (step 4).
        limits: dict[str, float] = {}
        start_q = self.cell.joint_positions
        start_flange = self.base_from_flange(start_q)
        for axis, label in ((2, "roll"), (0, "pitch"), (1, "yaw")):
            cap = s.roll_limit_deg if label == "roll" else s.tilt_limit_deg
            for sign in (1, -1):
                key = f"{label}{'+' if sign > 0 else '-'}"
                # Waypoints every `tilt_waypoint_deg` out to the cap (each solved from the
                # last, so the joints move little and the board tilts about its axis
                # only), driven through while the camera looks every `tilt_step_deg`.
                waypoints, seed_q = [], start_q
                for angle in [*np.arange(s.tilt_waypoint_deg, cap - 1e-9, s.tilt_waypoint_deg), cap]:
                    pose = start_board @ _axis_rotation(axis, sign * math.radians(angle))
                    q = self.flange_target(pose, fit.flange_from_board, near=seed_q)
                    if q is None or np.abs(q - seed_q).max() > 1.0:
                        break  # unreachable, or only by swinging the arm around
                    waypoints.append(q)
                    seed_q = q
                if not waypoints or not self.move_to(start_q):
                    self.progress(f"{name}: no tilt search {key}: " + ("unreachable" if not waypoints else "no way back to the start"))
                    limits[key] = 0.0
                    continue
                search = _TiltSearch(self, name, start_flange, fit.flange_from_board, axis, sign, s.tilt_step_deg)
                for q in waypoints:
                    if not self.move_through(q, search.watch, self.cell.config.time_step) or search.stopped:
                        break
                # Back off to the last tilt that was seen, and keep a still frame there.
                limits[key] = float(min(search.angle, cap))
                if search.q is not None and not self._full(name) and self.move_to(search.q):
                    obs = self.observe(name, tilted=True)
                    if obs is not None:
                        obs.phase = "tilt"
                    self._accept(obs)
        self.tilt_limits[name] = limits
        self.progress(
            f"{name}: tilt limits " + ", ".join(f"{k} {v:.0f}°" for k, v in limits.items())
            + f" ({self.motion_time - motion_before:.0f} s of motion so far)"
        )
        fit = self._fit(name, K0, d0, fit.flange_from_board, estimate_mount=True, threshold=loose)
        # Step 5: staged trajectory, re-aimed after every accepted frame.
        distance = float(np.linalg.norm((np.linalg.inv(fit.base_from_camera) @ start_board)[:3, 3]))
        w, h = cam.sensor.width, cam.sensor.height
        half_fov = np.array([(w / 2) / K0[0, 0], (h / 2) / K0[1, 1]])
        board_half = np.array(self.board.size) / 2
        tilts = [(0, 1), (1, 1), (0, -1), (1, -1), (2, 1), (2, -1)]
        n_pos = 0
        # Each position is visited at every distance in turn (Paper I runs the whole
        # trajectory again 20 % farther; interleaved, a run cut short by `max_frames`
        # still has both distances, which fix the focal length).
        for radius, count in zip(s.stage_radii, s.stage_positions):
            for j in range(count):
                tilted = s.tilt_fraction > 0 and n_pos % 2 == 1
                tilt = np.eye(4)
                if tilted:
                    axis, sign = tilts[(n_pos // 2) % len(tilts)]
                    label = ["pitch", "yaw", "roll"][axis]
                    lim = limits.get(f"{label}{'+' if sign > 0 else '-'}", 0.0)
                    tilt = _axis_rotation(axis, sign * math.radians(s.tilt_fraction * lim))
                n_pos += 1
                for factor in s.distance_factors:
                    if self._full(name):
                        break
                    d = distance * factor
                    # Where the board's centre may go and keep the whole board in the image.
                    usable = np.maximum(half_fov - 1.3 * board_half.max() / d, 0.02)
                    phase = 2 * math.pi * j / count + (math.pi / 4 if count == 4 else 0.0)
                    xy = radius * usable * np.array([math.cos(phase), math.sin(phase)])
                    ray = np.array([xy[0], xy[1], 1.0])
                    centre = d * ray / np.linalg.norm(ray)
                    # Face the camera: board z toward it, board x along the image's x.
                    zb = -centre / np.linalg.norm(centre)
                    xb = np.array([1.0, 0.0, 0.0]) - zb[0] * zb
                    xb /= np.linalg.norm(xb)
                    cam_from_board = np.eye(4)
                    cam_from_board[:3, 0], cam_from_board[:3, 1], cam_from_board[:3, 2] = xb, np.cross(zb, xb), zb
                    cam_from_board[:3, 3] = centre
                    cam_from_board = cam_from_board @ tilt
                    if not self.reach_board_pose(fit.base_from_camera @ cam_from_board, fit.flange_from_board):
                        continue  # unreachable or colliding: skip (Paper I)
                    obs = self.observe(name, tilted=tilted)
                    if obs is not None:
                        obs.distance_factor, obs.radius, obs.slot = factor, radius, j
                    if self._accept(obs):
                        fit = self._fit(name, K0, d0, fit.flange_from_board, estimate_mount=True, threshold=loose)
        self.progress(f"{name}: {len(self.observations[name])} frames in {self.motion_time - motion_before:.0f} s of motion")
        # Steps 6-7: lenses, then eye-to-hand again through the corrected lenses.
        return self.finish(name)

    def finish(self, name: str, observations: list[Observation] | None = None, *, screened: bool = False) -> CameraCalibration:
        """Steps 6-7 from the frames (the camera's accepted ones, or `observations`):
        Zhang's method for each lens (Paper I), refined with the robot as the rig
        (`calibrate_lens_on_robot`), the colour-depth offset, and eye-to-hand again
        through the corrected lens."""
        obs = self.observations[name] if observations is None else observations
        cam = self.camera(name)
        if len(obs) < 3:
            raise TooFewFrames(name, len(obs), 3)
        if not cam.sensor.has_depth:
            return self._finish_colour_only(name, obs, screened)
        t = time.perf_counter()
        zhang = calibrate_lens(
            [o.ir for o in obs], self.board_points, cam.sensor.intrinsics, camera=name, lens_model=self.settings.lens_model
        )
        self.solver_time += time.perf_counter() - t
        # The mount from the depth corners through Zhang's lens, then the rig; the lens
        # and the mount are refined in turn (each pass: the rig's lens and pose from the
        # pixels, the mount from the depth corners through that lens).
        fit = self._fit(
            name, zhang.K, zhang.distortion, self.settings.mount, estimate_mount=True, obs=obs,
            threshold=self.settings.ransac_threshold_uncorrected,
        )
        depth_lens = zhang
        depth_error = DepthBias()
        for _ in range(self.settings.refinement_passes):
            t = time.perf_counter()
            depth_lens, base_from_ir = self._lens_on_robot(
                name, obs, [o.ir for o in obs], fit.flange_from_board, depth_lens.K, depth_lens.distortion
            )
            self.solver_time += time.perf_counter() - t
            if not screened:
                # A frame the lens and pose cannot explain (a corner found in the wrong
                # place) is dropped once, and everything is solved again without it.
                good = self._explained(obs, [o.ir for o in obs], fit.flange_from_board, depth_lens, base_from_ir)
                if not good.all():
                    self.progress(f"{name}: {int((~good).sum())} frame(s) the lens and pose cannot explain dropped")
                    return self.finish(name, [o for o, g in zip(obs, good) if g], screened=True)
                screened = True
            previous = fit.flange_from_board
            if self.settings.depth_error_terms:
                t = time.perf_counter()
                depth_error = self.depth_error(obs, depth_lens.K, depth_lens.distortion, base_from_ir, previous)
                self.solver_time += time.perf_counter() - t
            fit = self._fit(
                name, depth_lens.K, depth_lens.distortion, previous, estimate_mount=True, obs=obs, depth_error=depth_error
            )
            if np.abs(fit.flange_from_board - previous).max() < 1e-5:
                break
        self._refuse_poor_lens(name, depth_lens)
        t = time.perf_counter()
        colour_lens, offset = None, None
        both = [o for o in obs if o.colour is not None]
        colour_detections = [o.colour for o in both if o.colour is not None]
        if cam.sensor.colour is not None and len(both) >= 8:
            colour_zhang = calibrate_lens(
                colour_detections, self.board_points, cam.sensor.colour.intrinsics, camera=name,
                lens_model=self.settings.lens_model,
            )
            colour_lens, base_from_colour = self._lens_on_robot(
                name, both, colour_detections, fit.flange_from_board, colour_zhang.K, colour_zhang.distortion
            )
            good = self._explained(both, colour_detections, fit.flange_from_board, colour_lens, base_from_colour)
            if not good.all() and good.sum() >= 8:
                both = [o for o, g in zip(both, good) if g]
                colour_detections = [d for d, g in zip(colour_detections, good) if g]
                colour_lens, base_from_colour = self._lens_on_robot(
                    name, both, colour_detections, fit.flange_from_board, colour_lens.K, colour_lens.distortion
                )
            offset = np.linalg.inv(base_from_ir) @ base_from_colour
        self.solver_time += time.perf_counter() - t
        pose = base_from_ir if self.settings.pose_from == "pixels" else fit.base_from_camera
        return CameraCalibration(
            name=name,
            base_from_camera=pose,
            depth_K=depth_lens.K,
            depth_distortion=depth_lens.distortion,
            depth_size=obs[0].ir.image_size,
            colour_K=None if colour_lens is None else colour_lens.K,
            colour_distortion=None if colour_lens is None else colour_lens.distortion,
            colour_size=None if colour_lens is None else colour_detections[0].image_size,
            depth_from_colour=offset,
            depth_error=None if depth_error.is_zero else depth_error.as_list(),
            flange_from_board=fit.flange_from_board,
            eye_to_hand_rmse=fit.rmse,
            depth_reprojection_rms=depth_lens.rms,
            colour_reprojection_rms=float("nan") if colour_lens is None else colour_lens.rms,
            zhang_reprojection_rms=zhang.rms,
            pose_agreement_m=float(np.linalg.norm(base_from_ir[:3, 3] - fit.base_from_camera[:3, 3])),
            frames=len(obs),
            corners=fit.corners,
            depth_region=_region([o.ir for o in obs]),
            colour_region=_region(colour_detections) if colour_lens is not None else None,
            start_q=[float(v) for v in self.start_poses[name][1]] if name in self.start_poses else None,
        )

    def _finish_colour_only(self, name: str, obs: list[Observation], screened: bool) -> CameraCalibration:
        """Steps 6-7 for a camera without depth: Zhang's method, AX = ZB for the pose and
        the mount, then the lens and pose refined with the robot as the rig, the mount
        from every frame's board pose in turn (the pose of the camera's own image)."""
        s = self.settings
        cam = self.camera(name)
        t = time.perf_counter()
        zhang = calibrate_lens([o.ir for o in obs], self.board_points, cam.sensor.intrinsics, camera=name, lens_model=s.lens_model)
        self.solver_time += time.perf_counter() - t
        fit = self._fit_from_pixels(name, zhang.K, zhang.distortion, s.mount, True, obs)
        lens, mount = zhang, fit.flange_from_board
        flanges = np.array([o.base_from_flange for o in obs])
        base_from_camera = fit.base_from_camera
        for _ in range(s.refinement_passes):
            t = time.perf_counter()
            lens, base_from_camera = self._lens_on_robot(name, obs, [o.ir for o in obs], mount, lens.K, lens.distortion)
            if not screened:
                good = self._explained(obs, [o.ir for o in obs], mount, lens, base_from_camera)
                if not good.all():
                    self.progress(f"{name}: {int((~good).sum())} frame(s) the lens and pose cannot explain dropped")
                    return self._finish_colour_only(name, [o for o, g in zip(obs, good) if g], True)
                screened = True
            # The pose and the mount that best explain every corner's pixel through the
            # refined lens (no depth to fix the mount with).
            previous = mount
            base_from_camera, mount, _ = refine_by_reprojection(
                [o.ir.corners for o in obs], flanges, self.board_points, lens.K, lens.distortion, base_from_camera, mount
            )
            self.solver_time += time.perf_counter() - t
            if np.abs(mount - previous).max() < 1e-5:
                break
        self._refuse_poor_lens(name, lens)
        return CameraCalibration(
            name=name,
            base_from_camera=base_from_camera,
            colour_K=lens.K,
            colour_distortion=lens.distortion,
            colour_size=obs[0].ir.image_size,
            flange_from_board=mount,
            eye_to_hand_rmse=fit.rmse,
            colour_reprojection_rms=lens.rms,
            zhang_reprojection_rms=zhang.rms,
            frames=len(obs),
            corners=len(obs) * len(self.board_points),
            colour_region=_region([o.ir for o in obs]),
            start_q=[float(v) for v in self.start_poses[name][1]] if name in self.start_poses else None,
        )

    def _refuse_poor_lens(self, name: str, lens) -> None:
        """A calibration whose lens and pose leave the corners too far off is refused."""
        limit = self.settings.max_reprojection_px
        if lens.rms > limit:
            raise DegeneratePoses(
                name, f"the lens and pose explain the corners only to {lens.rms:.1f} px rms (> {limit} px): too few or too similar frames"
            )

    def _corners_in_base(self, obs: list[Observation], mount: np.ndarray) -> np.ndarray:
        """Every frame's board corners placed in the base frame by forward kinematics."""
        return np.concatenate([apply_pose(o.base_from_flange @ mount, self.board_points) for o in obs])

    def _explained(self, obs, detections, mount, lens, base_from_camera) -> np.ndarray:
        """Per frame: do the lens and pose reproject its corners within max(1 px, 4× the
        median frame's rms)?"""
        errors = reprojection_errors(
            self._corners_in_base(obs, mount),
            np.concatenate([d.corners for d in detections]), lens.K, lens.distortion, base_from_camera,
        ).reshape(len(obs), -1)
        per_frame = np.sqrt((errors**2).mean(axis=1))
        return per_frame <= max(1.0, 4 * float(np.median(per_frame)))

    def _lens_on_robot(self, name, obs, detections, mount, K_guess, dist_guess):
        pixels = np.concatenate([d.corners for d in detections])
        return calibrate_lens_on_robot(
            self._corners_in_base(obs, mount), pixels, detections[0].image_size, K_guess, dist_guess, camera=name, lens_model=self.settings.lens_model
        )

    def run(self, names: list[str] | None = None) -> dict[str, CameraCalibration]:
        """Calibrate the named fixed cameras (default: every fixed camera)."""
        names = names or [c.name for c in self.cell.cameras if c.mount is None]
        self.sweep(names)
        out = {}
        for name in names:
            self.progress(f"calibrating {name}")
            out[name] = self.calibrate_camera(name)
        return out

    def run_to_file(self, path, names: list[str] | None = None) -> dict[str, CameraCalibration]:
        """`run`, then merge the cameras into the calibration file at `path` (the other
        cameras keep their entries). Nothing is written unless every camera succeeded: a
        `CalibrationError` leaves the file as it was."""
        from pathlib import Path

        path = Path(path)
        results = self.run(names)
        try:
            existing = Calibration.load(path) if path.exists() else Calibration()
        except CalibrationFileError as exc:
            self.progress(f"{exc}: writing a new file")
            existing = Calibration()
        existing.merged(results).save(path)
        return results
