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
are skipped (`earcore.calibration.motion`). Simulated robot time is counted
(`motion_time`). The fits are pure functions of the observations
(`earcore.calibration.estimate`); this module decides where the robot goes and what
each camera sees there.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from earcore.calibration.board import Checkerboard, Detection, detect_board
from earcore.calibration.config import CalibrationConfig
from earcore.calibration.errors import BoardNotSeen, CalibrationError, CalibrationFileError, PoorCalibration
from earcore.calibration.estimate import Estimator, Observation, SensorSpec
from earcore.calibration.eye_to_hand import EyeToHand
from earcore.calibration.motion import BoardMotion
from earcore.calibration.store import Calibration, CameraCalibration
from earcore.transforms import axis_angle_matrix, rotation_from_vector, rotation_vector

__all__ = ["Calibrator", "refuse_uncertain"]


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    """The 4×4 turn by `angle` about the x, y or z axis (0, 1, 2)."""
    m = np.eye(4)
    m[:3, :3] = axis_angle_matrix(np.eye(3)[axis], angle)
    return m


class _TiltSearch:
    """Watches one camera while the board tilts about one of its axes: at every `step`
    degrees of tilt in the searched direction (the board's rotation since the start,
    as a rotation vector, along that axis) the camera looks; the first miss stops the
    motion. Tilt the other way (on the way over from the previous search) is ignored."""

    def __init__(
        self, calibrator: Calibrator, camera: str, start_flange: np.ndarray, mount: np.ndarray, axis: int, sign: int, step: float
    ) -> None:
        self.calibrator, self.camera, self.step = calibrator, camera, step
        self.base_from_flange = calibrator.motion.base_from_flange
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
        turn = self.start.T @ self.base_from_flange(q)[:3, :3]
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


def refuse_uncertain(result: CameraCalibration, config: CalibrationConfig) -> None:
    """Raise `PoorCalibration`, naming the camera and what its uncertainty is made of,
    when its pose is less certain than `config.max_pose_sigma_m` / `_deg` accept."""
    limit_m, limit_deg = config.max_pose_sigma_m, config.max_pose_sigma_deg
    over_m = limit_m is not None and not result.pose_sigma_m <= limit_m
    over_deg = limit_deg is not None and not result.pose_sigma_deg <= limit_deg
    if not (over_m or over_deg):
        return
    limits = [f"{1000 * limit_m:.1f} mm" if limit_m is not None else "", f"{limit_deg:g}°" if limit_deg is not None else ""]
    parts = [f"the pose from pixels alone ±{1000 * result.pixel_pose_sigma_m:.1f} mm / ±{result.pixel_pose_sigma_deg:.2f}°"]
    if result.has_depth:
        parts.append(f"the poses from pixels and from depth {1000 * result.pose_agreement_m:.1f} mm / {result.pose_agreement_deg:.2f}° apart")
    if config.max_frames is not None and result.frames < config.max_frames:
        parts.append(f"{result.frames} of {config.max_frames} frames kept (the rest out of reach, out of view or not explained by the fit)")
    raise PoorCalibration(
        result.name,
        f"pose uncertain to ±{1000 * result.pose_sigma_m:.1f} mm / ±{result.pose_sigma_deg:.2f}° (1σ), beyond "
        f"{' / '.join(x for x in limits if x)}: " + "; ".join(parts),
    )


class _Aim:
    """Board poses in one camera's frame that keep the whole board in its image: the
    board's centre at `radius` (fraction of the usable half-field of view) in direction
    `phase` around the image centre, `factor` times the start distance away."""

    def __init__(self, width: int, height: int, K: np.ndarray, board_half: np.ndarray, distance: float) -> None:
        self.half_fov = np.array([(width / 2) / K[0, 0], (height / 2) / K[1, 1]])
        self.board_half, self.distance = board_half, distance

    def facing(self, radius: float, phase: float, factor: float, *, toward: np.ndarray | None = None, blend: float = 0.0) -> np.ndarray:
        """camera_from_board: the board's face toward the camera, its x along the image's
        x; with `toward` (a camera_from_board rotation), turned `blend` of the way to it."""
        d = self.distance * factor
        usable = np.maximum(self.half_fov - 1.3 * self.board_half.max() / d, 0.02)
        xy = radius * usable * np.array([math.cos(phase), math.sin(phase)])
        ray = np.array([xy[0], xy[1], 1.0])
        centre = d * ray / np.linalg.norm(ray)
        zb = -centre / np.linalg.norm(centre)
        xb = np.array([1.0, 0.0, 0.0]) - zb[0] * zb
        xb /= np.linalg.norm(xb)
        out = np.eye(4)
        out[:3, 0], out[:3, 1], out[:3, 2] = xb, np.cross(zb, xb), zb
        if toward is not None and blend > 0:
            out[:3, :3] = out[:3, :3] @ rotation_from_vector(blend * rotation_vector(out[:3, :3].T @ toward))
        out[:3, 3] = centre
        return out


class Calibrator:
    """Runs Algorithm 1 on a `SimulatedCell` (or anything with its robot and camera
    interface) holding the checkerboard."""

    def __init__(
        self,
        cell,
        config: CalibrationConfig | None = None,
        *,
        board: Checkerboard = Checkerboard(),
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.cell = cell
        self.config = config or CalibrationConfig()
        self.board = board
        self.board_points = board.inner_corners()
        self.model = cell.model
        self.progress = progress or (lambda message: None)
        self.rng = np.random.default_rng(self.config.seed)
        #: The robot's side: motions, IK, the simulated time spent moving.
        self.motion = BoardMotion(cell, self.config, self.rng)
        #: The fits: pure functions of the observations.
        self.estimator = Estimator(self.board_points, self.config, self.progress)
        self.observations: dict[str, list[Observation]] = {}
        self.start_poses: dict[str, tuple[float, np.ndarray]] = {}
        self.tilt_limits: dict[str, dict[str, float]] = {}

    # --- set-up ---------------------------------------------------------------

    @property
    def motion_time(self) -> float:
        """Simulated seconds the robot spent moving."""
        return self.motion.motion_time

    @property
    def solver_time(self) -> float:
        """Seconds spent in the solvers (lens and eye-to-hand fits)."""
        return self.estimator.solver_time

    def camera(self, name: str):
        for cam in self.cell.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r}; cameras: {[c.name for c in self.cell.cameras]}")

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
            return Observation(name, q, self.motion.base_from_flange(q), ir, None, np.zeros((0, 0, 0), np.float32), (0, 0), tilted)
        lo = np.maximum(np.floor(ir.corners.min(axis=0)).astype(int) - 40, 0)
        hi = np.ceil(ir.corners.max(axis=0)).astype(int) + 40
        # The board and robot are still: frames differ by the sensor's noise only.
        region = true_depth[lo[1] : hi[1], lo[0] : hi[0]]
        origin = (int(lo[0]), int(lo[1]))
        depth = np.stack([cam.sensor.corrupt(region, cam.rng, origin) for _ in range(self.config.depth_frames)]).astype(np.float32)
        col = detect_board(cam.render_colour(), self.board) if (colour and cam.sensor.colour is not None) else None
        q = self.cell.joint_positions
        return Observation(name, q, self.motion.base_from_flange(q), ir, col, depth, origin, tilted)


    # --- Algorithm 1 -----------------------------------------------------------

    def sweep(self, names: list[str]) -> None:
        """Step 1: the board on an upside-down "L" turns 360° about the base while every
        camera watches; each keeps the joint state where it saw the board nearest its
        image centre."""
        s = self.config
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
            if not self.motion.reach_board_pose(self.model.base @ board_pose, s.mount):
                raise CalibrationError("all", f"the sweep pose (elevation {elevation}°) is unreachable")
            q0 = self.cell.joint_positions
            self.motion.home = q0.copy()
            lo, hi = self.model.joint_limits[0]
            # One continuous turn, the way the base joint's limits allow.
            turn = min(2 * math.pi, hi - q0[0]) if hi - q0[0] >= q0[0] - lo else -min(2 * math.pi, q0[0] - lo)
            q1 = q0.copy()
            q1[0] += turn
            self.progress(f"sweep at {elevation:.0f}° elevation: turning {math.degrees(abs(turn)):.0f}° about the base")
            before = self.motion.motion_time

            def watch(q: np.ndarray) -> bool:
                for name in names:
                    detection = self.detect(name)
                    if detection is None:
                        continue
                    score = detection.distance_from_image_centre()
                    if name not in self.start_poses or score < self.start_poses[name][0]:
                        self.start_poses[name] = (score, q.copy())
                return True

            self.motion.move_through(q1, watch, s.watch_period, shortest=False)
            self.progress(f"sweep done: {self.motion.motion_time - before:.0f} s of motion; seen by {sorted(self.start_poses)}")
        for name in names:
            if name not in self.start_poses:
                sensor = self.camera(name).sensor
                raise BoardNotSeen(
                    name,
                    f"not during the 360° sweep at elevations {list(s.sweep_elevations_deg)}°, "
                    f"in images of {sensor.width}×{sensor.height} pixels: out of view, or too small to find",
                )


    def _board_in_camera(self, fit: EyeToHand, obs: Observation) -> np.ndarray:
        return np.linalg.inv(fit.base_from_camera) @ obs.base_from_flange @ fit.flange_from_board

    def _accept(self, obs: Observation | None) -> bool:
        if obs is None:
            return False
        self.observations[obs.camera].append(obs)
        return True

    def _full(self, name: str) -> bool:
        m = self.config.max_frames
        return m is not None and len(self.observations[name]) >= m

    def calibrate_camera(self, name: str) -> CameraCalibration:
        s = self.config
        cam = self.camera(name)
        spec = SensorSpec.of(cam.sensor)
        K0, d0 = spec.intrinsics, np.zeros(5)  # the datasheet's pinhole, no lens model yet
        if name not in self.start_poses:
            self.sweep([name])
        self.observations[name] = []
        motion_before = self.motion.motion_time
        # Steps 1-2: the start pose and a first eye-to-hand with the mount as designed.
        if not self.motion.go_to(self.start_poses[name][1]):
            raise CalibrationError(name, "the start pose cannot be reached")
        first = self.observe(name)
        if first is None:
            raise BoardNotSeen(name, "at its start pose")
        first.phase = "start"
        self._accept(first)
        loose = s.ransac_threshold_uncorrected
        fit = self.estimator.fit(self.observations[name], spec, K0, d0, s.mount, estimate_mount=False, threshold=loose)
        start_board = fit.base_from_camera @ self._board_in_camera(fit, self.observations[name][0])
        # Step 3: tilt limits, both ways about each board axis. The frame at each limit
        # is kept: those tilted-in-place frames fix the mount (step 4).
        limits: dict[str, float] = {}
        start_q = self.cell.joint_positions
        start_flange = self.motion.base_from_flange(start_q)
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
                    q = self.motion.flange_target(pose, fit.flange_from_board, near=seed_q)
                    if q is None or np.abs(q - seed_q).max() > 1.0:
                        break  # unreachable, or only by swinging the arm around
                    waypoints.append(q)
                    seed_q = q
                if not waypoints or not self.motion.move_to(start_q):
                    self.progress(f"{name}: no tilt search {key}: " + ("unreachable" if not waypoints else "no way back to the start"))
                    limits[key] = 0.0
                    continue
                search = _TiltSearch(self, name, start_flange, fit.flange_from_board, axis, sign, s.tilt_step_deg)
                for q in waypoints:
                    if not self.motion.move_through(q, search.watch, self.cell.config.time_step) or search.stopped:
                        break
                # Back off to the last tilt that was seen, and keep a still frame there.
                limits[key] = float(min(search.angle, cap))
                if search.q is not None and not self._full(name) and self.motion.move_to(search.q):
                    obs = self.observe(name, tilted=True)
                    if obs is not None:
                        obs.phase = "tilt"
                    self._accept(obs)
        self.tilt_limits[name] = limits
        self.progress(
            f"{name}: tilt limits " + ", ".join(f"{k} {v:.0f}°" for k, v in limits.items())
            + f" ({self.motion.motion_time - motion_before:.0f} s of motion so far)"
        )
        fit = self.estimator.fit(self.observations[name], spec, K0, d0, fit.flange_from_board, estimate_mount=True, threshold=loose)
        # Step 5: staged trajectory, re-aimed after every accepted frame.
        distance = float(np.linalg.norm((np.linalg.inv(fit.base_from_camera) @ start_board)[:3, 3]))
        start_turn = (np.linalg.inv(fit.base_from_camera) @ start_board)[:3, :3]
        aim = _Aim(cam.sensor.width, cam.sensor.height, K0, np.array(self.board.size) / 2, distance)
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
                phase = 2 * math.pi * j / count + (math.pi / 4 if count == 4 else 0.0)
                for factor in s.distance_factors:
                    if self._full(name):
                        break
                    target = aim.facing(radius, phase, factor) @ tilt
                    fit = self._capture(name, spec, K0, d0, fit, target, tilted, (factor, radius, j))
        # Step 5b: Paper I skips what the robot cannot reach; with a frame budget, the
        # frames still missing are sought between the stages' positions, facing the
        # camera and then turned halfway to the start pose's board (which the camera saw
        # there), so that a camera the robot serves only at an angle still gets its frames.
        if s.max_frames is not None:
            tried, before = 0, len(self.observations[name])
            blends = (0.0, 0.5) if s.tilt_fraction > 0 else (0.0,)
            for radius, count in zip(s.topup_radii, s.topup_positions):
                for j in range(count):
                    phase = 2 * math.pi * (j + 0.5) / count + (math.pi / 4 if count == 4 else 0.0)
                    for blend in blends:
                        for factor in s.topup_distance_factors:
                            if self._full(name):
                                break
                            target = aim.facing(radius, phase, factor, toward=start_turn, blend=blend)
                            tried += 1
                            fit = self._capture(name, spec, K0, d0, fit, target, blend > 0, (factor, radius, j))
            if tried and not self._full(name):
                got = len(self.observations[name]) - before
                self.progress(
                    f"{name}: {len(self.observations[name])} of {s.max_frames} frames; of {tried} further board poses "
                    f"tried, {got} gave a frame, the others were out of reach or out of view"
                )
        self.progress(f"{name}: {len(self.observations[name])} frames in {self.motion.motion_time - motion_before:.0f} s of motion")
        # Steps 6-7: lenses, then eye-to-hand again through the corrected lenses.
        result = self.finish(name)
        refuse_uncertain(result, self.config)
        return result

    def _capture(self, name, spec, K0, d0, fit: EyeToHand, camera_from_board: np.ndarray, tilted: bool, where) -> EyeToHand:
        """Bring the board to `camera_from_board` (as the current fit places the camera),
        keep the frame if the camera sees it, and re-fit with it. Unreachable or colliding
        poses are skipped (Paper I)."""
        if not self.motion.reach_board_pose(fit.base_from_camera @ camera_from_board, fit.flange_from_board):
            return fit
        obs = self.observe(name, tilted=tilted)
        if obs is not None:
            obs.distance_factor, obs.radius, obs.slot = where
        if not self._accept(obs):
            return fit
        loose = self.config.ransac_threshold_uncorrected
        return self.estimator.fit(self.observations[name], spec, K0, d0, fit.flange_from_board, estimate_mount=True, threshold=loose)

    def finish(self, name: str, observations: list[Observation] | None = None) -> CameraCalibration:
        """Steps 6-7 (`Estimator.finish`) from camera `name`'s accepted frames, or from
        `observations`."""
        obs = self.observations[name] if observations is None else observations
        start = self.start_poses.get(name)
        return self.estimator.finish(name, obs, SensorSpec.of(self.camera(name).sensor), start_q=None if start is None else start[1])


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
        # Read before the robot moves: a file that is not a calibration this can read
        # (another file, an entry it cannot parse) is refused, not overwritten.
        existing = Calibration()
        if path.is_dir():
            raise CalibrationFileError(f"{path} is a folder: give a calibration file to write")
        if path.exists():
            try:
                existing = Calibration.load(path)
            except CalibrationFileError as exc:
                raise CalibrationFileError(f"{exc}; not overwriting it: give another file, or move it away") from exc
        results = self.run(names)
        existing.merged(results).save(path)
        return results
