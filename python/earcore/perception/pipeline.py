"""Paper II's pipeline (Fig. 1), per frame: every camera's depth → points in the base
frame (calibrated poses, refined once by ICP if asked) → crop around the robot → the
cameras' clouds merged → voxel grid → statistical outlier removal → self-filter at the
current joint state → octree insertion (each point's ray from the camera that saw it)
→ end of frame (danger decay).

Voxel grid before outlier removal (the paper does the reverse): the neighbour search
then runs on ~10× fewer points; the result differs only in which isolated points go.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

import earcore
from earcore.cloud import box_voxel_centres, voxel_codes
from earcore.depth_error import DepthBias, radius2_grid
from earcore.robots import RobotModel
from earcore.sim.camera import Frame
from earcore.sim.config import PerceptionConfig

__all__ = ["FrameReport", "PerceptionPipeline", "perturb_pose"]

STAGES = ("points", "crop", "voxel_grid", "outliers", "self_filter", "insert", "end_frame")


@dataclass
class FrameReport:
    time: float
    #: Seconds per stage (summed over cameras).
    timings: dict[str, float] = field(default_factory=dict)
    points_in: int = 0
    points_inserted: int = 0
    removed_as_robot: int = 0
    danger_voxels: int = 0
    current_obstacles: int = 0
    #: With `track_body` (simulation): the tracked body's points after the voxel grid
    #: (centroids where its pixels dominate) and how many of them were inserted.
    tracked_points: int = 0
    tracked_inserted: int = 0

    @property
    def total(self) -> float:
        return sum(self.timings.values())


#: Far points (beyond the crop) whose rays clear space: about this many per image row
#: and column (0.55° apart for a Kinect V2: 1.9 cm at 2 m, under the map's 5 cm cells).
FAR_RAYS_ACROSS = 128


@functools.lru_cache(maxsize=8)
def _pixel_grid(shape: tuple[int, int]) -> np.ndarray:
    """Flat mask of an image's pixels on a grid about FAR_RAYS_ACROSS wide (every
    stride-th row and column)."""
    height, width = shape
    stride = max(1, round(width / FAR_RAYS_ACROSS))
    grid = np.zeros(shape, dtype=bool)
    grid[::stride, ::stride] = True
    grid.flags.writeable = False  # shared by every frame of that shape (cached)
    return grid.reshape(-1)


def _in_sorted(sorted_values: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Whether each query is in the ascending array `sorted_values` (binary search:
    the queries are few, the array long)."""
    if not len(sorted_values):
        return np.zeros(len(queries), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_values, queries), len(sorted_values) - 1)
    return sorted_values[at] == queries


def _cut_at_sphere(points: np.ndarray, sensor: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Where the segments from `sensor` to `points` leave the sphere (`center`,
    `radius`); segments that do not pass through it are dropped."""
    d = points - sensor
    w = sensor - center
    a = np.einsum("ij,ij->i", d, d)
    b = d @ w
    disc = b * b - a * (w @ w - radius * radius)
    ok = (disc > 0) & (a > 0)
    root = np.sqrt(np.where(ok, disc, 0.0))
    safe = np.where(ok, a, 1.0)
    t_in, t_out = (-b - root) / safe, (-b + root) / safe
    ok &= (t_out > 0) & (t_in < 1)  # the segment meets the sphere
    return sensor + np.minimum(t_out[ok], 1.0)[:, None] * d[ok]


def perturb_pose(pose: np.ndarray, translation: float, rotation: float, rng: np.random.Generator) -> np.ndarray:
    """A pose moved by `translation` metres and turned by `rotation` radians in random
    directions (to stand in for calibration error)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + np.sin(rotation) * k + (1 - np.cos(rotation)) * k @ k
    shift = rng.normal(size=3)
    out = pose.copy()
    out[:3, :3] = r @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + translation * shift / np.linalg.norm(shift)
    return out


class PerceptionPipeline:
    def __init__(
        self, config: PerceptionConfig, robot: RobotModel, *, seed: int = 0, fixed_cameras: set[str] | None = None
    ) -> None:
        self.config = config
        self.robot = robot
        self.tree = earcore.OcTree(config.resolution)
        self.tree.danger_alpha = config.danger_alpha
        self.tree.decay_mode = config.decay_mode
        self.rng = np.random.default_rng(seed)
        #: base_from_camera per camera name, as the loop believes them (calibrated).
        self.poses: dict[str, np.ndarray] = {}
        #: (K, distortion) per camera name from a calibration; else the frame's own.
        self.intrinsics: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        #: Calibrated depth error per camera name, taken out of its depth images.
        self.depth_errors: dict[str, DepthBias] = {}
        self._radius2: dict[str, np.ndarray] = {}
        self._refined = not config.refine_poses
        self._last_time: float | None = None
        #: Cameras that do not move with the robot (only these are refined by ICP).
        self.fixed_cameras = fixed_cameras
        #: Simulation only: follow the points of this segmentation id (the robot's
        #: pybullet body) through the pipeline to count how many reach the map.
        self.track_body: int | None = None

    def set_pose(self, camera: str, base_from_camera: np.ndarray) -> None:
        """The calibrated pose of a fixed camera (used instead of the frame's)."""
        self.poses[camera] = np.asarray(base_from_camera, dtype=np.float64)

    def set_intrinsics(self, camera: str, K: np.ndarray, distortion) -> None:
        """The calibrated depth-camera intrinsics of a camera (used instead of the frame's)."""
        self.intrinsics[camera] = (np.asarray(K, dtype=np.float64), np.asarray(distortion, dtype=np.float64))

    def load_calibration(self, calibration) -> None:
        """Poses, depth intrinsics and depth errors of every camera in a
        `earcore.calibration.Calibration`."""
        for name, cam in calibration.cameras.items():
            if not cam.has_depth:
                continue  # a colour-only camera adds nothing to the map
            self.set_pose(name, cam.base_from_camera)
            self.set_intrinsics(name, cam.depth_K, cam.depth_distortion)
            self.depth_errors[name] = cam.depth_bias
            self._radius2.pop(name, None)

    def _depth_of(self, frame: Frame, K: np.ndarray) -> np.ndarray:
        """The frame's depth image with the camera's calibrated depth error taken out."""
        bias = self.depth_errors.get(frame.camera)
        if bias is None or bias.is_zero:
            return frame.depth
        h, w = frame.depth.shape
        rho2 = self._radius2.get(frame.camera)
        if rho2 is None or rho2.shape != (h, w):
            rho2 = self._radius2[frame.camera] = radius2_grid(K, w, h)
        return bias.correct(frame.depth, rho2)

    def _points_of(self, frame: Frame, **kwargs):
        K, distortion = self.intrinsics.get(frame.camera, (frame.K, frame.distortion))
        return earcore.depth_to_points(
            self._depth_of(frame, K), K[0, 0], K[1, 1], K[0, 2], K[1, 2], distortion=distortion,
            max_depth=self.config.max_range, **kwargs,
        )

    def _pose_of(self, frame: Frame) -> np.ndarray:
        """The pose the loop believes: the calibrated one if set; for a fixed camera with
        `pose_error`, its true pose perturbed once (a constant calibration error)."""
        if frame.camera in self.poses:
            return self.poses[frame.camera]
        t, r = self.config.pose_error
        fixed = self.fixed_cameras is None or frame.camera in self.fixed_cameras
        if (t > 0 or r > 0) and fixed:
            self.poses[frame.camera] = perturb_pose(frame.base_from_camera, t, r, self.rng)
            return self.poses[frame.camera]
        return frame.base_from_camera

    def add_support(self, box_min, box_max, *, keep_clear: float = 0.25) -> int:
        """Put the robot's support (its table: a box below z = 0 in the base frame) into
        the map as occupied voxels, except within `keep_clear` metres (horizontally) of
        the robot's base, where the robot's mount is and its padded shoulder and upper arm
        dip to the table top (a UR5's do). Returns the voxels added."""
        centres = box_voxel_centres(box_min, box_max, self.tree.resolution)
        base = self.robot.base[:3, 3]
        centres = centres[np.linalg.norm(centres[:, :2] - base[:2], axis=1) > keep_clear]
        for _ in range(8):  # hits until the log-odds clamp: the table stays put
            self.tree.update_nodes(centres, occupied=True)
        return len(centres)

    def refine(self, frames: list[Frame]) -> None:
        """Paper II's one-off ICP refinement of the fixed cameras against each other."""
        fixed = [f for f in frames if self.fixed_cameras is None or f.camera in self.fixed_cameras]
        if len(fixed) < 2:
            return
        poses = [self._pose_of(f) for f in fixed]
        origin = self.robot.base[:3, 3]
        clouds = []
        for f, pose in zip(fixed, poses):
            local = self._points_of(f)
            # Only the working volume: the far floor and walls are planes that let
            # the alignment slide.
            in_base = local @ pose[:3, :3].T + pose[:3, 3]
            clouds.append(local[np.linalg.norm(in_base - origin, axis=1) <= self.config.crop_radius + 0.5])
        refined = earcore.refine_camera_poses(clouds, poses, max_correspondence_distance=0.08)
        for f, pose in zip(fixed, refined):
            self.poses[f.camera] = pose

    def process(self, frames: list[Frame], q: np.ndarray, time_s: float) -> FrameReport:
        """Integrate the frames captured at `time_s` with the robot at joint state `q`."""
        c = self.config
        report = FrameReport(time_s, {s: 0.0 for s in STAGES})
        if not self._refined and frames:
            self.refine(frames)
            self._refined = True
        origin = self.robot.base[:3, 3]
        # Per camera: points in the base frame, cropped (Paper II merges the cameras'
        # clouds, then pre-processes the merged cloud once).
        clouds, origins, columns, lows, far = [], [], [], [], []
        tracking = self.track_body is not None
        t0 = time.perf_counter()
        for frame in frames:
            pose = self._pose_of(frame)
            pts, pixels = self._points_of(frame, base_from_camera=pose, return_pixels=True)
            report.points_in += len(pts)
            t1 = time.perf_counter()
            all_pts = pts
            pts, idx = earcore.crop(pts, center=origin, radius=c.crop_radius, return_index=True)
            if c.clear_beyond_crop and len(idx) < len(all_pts):
                # About FAR_RAYS_ACROSS rays across the image are plenty (they are thinned to
                # one per map cell where they leave the sphere anyway) and keep this cheap:
                # at full resolution the far points are most of a Kinect's frame.
                on_grid = np.flatnonzero(_pixel_grid(frame.depth.shape)[pixels])
                beyond = on_grid[~_in_sorted(idx, on_grid)]
                far.append(_cut_at_sphere(all_pts.take(beyond, axis=0), pose[:3, 3], origin, c.crop_radius))
            else:
                far.append(np.zeros((0, 3)))
            if c.min_height is not None:
                # Low points (the table) only clear the space in front of them.
                above = pts[:, 2] >= c.min_height
                lows.append(np.compress(~above, pts, axis=0))
                pts, idx = np.compress(above, pts, axis=0), idx[above]
            else:
                lows.append(np.zeros((0, 3)))
            robot = np.zeros(len(pts))
            if tracking and frame.segmentation is not None:
                robot = (frame.segmentation.reshape(-1)[pixels[idx]] == self.track_body).astype(np.float64)
            t2 = time.perf_counter()
            # A first voxel grid per camera shrinks the merge (and keeps labels cheap).
            if c.voxel_size > 0 and len(pts):
                if tracking:
                    pts, robot = earcore.voxel_downsample(pts, c.voxel_size, robot)
                else:
                    pts = earcore.voxel_downsample(pts, c.voxel_size)
                    robot = np.zeros(len(pts))
            t3 = time.perf_counter()
            report.timings["points"] += t1 - t0
            report.timings["crop"] += t2 - t1
            report.timings["voxel_grid"] += t3 - t2
            t0 = t3
            clouds.append(pts)
            origins.append(pose[:3, 3])
            columns.append(robot)
        if not clouds or not sum(len(p) for p in clouds):
            t5 = time.perf_counter()
            self._insert_free_rays(origins, lows, far)
            report.timings["insert"] += time.perf_counter() - t5
            return self._close_frame(report, time_s)
        # One voxel grid over the merged cloud; each centroid remembers which camera
        # contributed most of its points (its ray is cast from there) and, in
        # simulation, the fraction of its points that were the tracked body's.
        n_cam = len(clouds)
        merged = np.vstack(clouds)
        values = np.zeros((len(merged), n_cam + 1))
        start = 0
        for i, (pts, robot) in enumerate(zip(clouds, columns)):
            values[start : start + len(pts), i] = 1.0
            values[start : start + len(pts), n_cam] = robot
            start += len(pts)
        t2 = time.perf_counter()
        if c.voxel_size > 0:
            pts, means = earcore.voxel_downsample(merged, c.voxel_size, values)
        else:
            pts, means = merged, values
        camera = np.argmax(means[:, :n_cam], axis=1)
        label = means[:, n_cam]
        t3 = time.perf_counter()
        if len(pts) > c.outlier_k:
            pts, idx = earcore.remove_statistical_outliers(pts, c.outlier_k, c.outlier_std_ratio, return_index=True)
            camera, label = camera[idx], label[idx]
        t4 = time.perf_counter()
        keep = self.robot.self_filter(pts, q, c.self_filter_margin)
        report.removed_as_robot += int((~keep).sum())
        if tracking:
            tracked = label > 0.5
            report.tracked_points += int(tracked.sum())
            report.tracked_inserted += int((tracked & keep).sum())
        pts, camera = np.compress(keep, pts, axis=0), camera[keep]
        t5 = time.perf_counter()
        self._insert_free_rays(origins, lows, far)
        for i, sensor_origin in enumerate(origins):
            mine = np.compress(camera == i, pts, axis=0)
            if len(mine):
                self.tree.insert_point_cloud(mine, sensor_origin, max_range=c.max_range)
                report.points_inserted += len(mine)
        t6 = time.perf_counter()
        for stage, dt in zip(STAGES[2:], (t3 - t2, t4 - t3, t5 - t4, t6 - t5)):
            report.timings[stage] += dt
        report = self._close_frame(report, time_s)
        t7 = time.perf_counter()
        self._clear_robot_volume(q)
        report.timings["self_filter"] += time.perf_counter() - t7
        return report

    def _insert_free_rays(self, origins, lows, far) -> None:
        """Per camera, rays that only clear space: to the table's points and to where far
        points' rays leave the crop sphere, thinned to one per map cell at their end
        (neighbouring rays cross nearly the same cells)."""
        for sensor_origin, low, beyond in zip(origins, lows, far):
            free = np.vstack([low, beyond]) if len(beyond) else low
            if len(free):
                free = earcore.voxel_downsample(free, self.tree.resolution)
                self.tree.insert_free_rays(free, sensor_origin, max_range=self.config.max_range)

    def _clear_robot_volume(self, q: np.ndarray) -> int:
        """Free the occupied voxels that touch the robot's bodies and were not seen in
        this frame. A robot point that slipped through the self-filter would otherwise
        stay for good (the robot hides its voxel from every camera) and put every plan
        that starts there in collision; an obstacle really touching the robot is seen
        again each frame and stays. Returns the voxels freed."""
        res = self.tree.resolution
        bodies = self.robot.bodies(q)
        r = bodies["radius"][:, None] + res
        lo = np.minimum(bodies["a"], bodies["b"]) - r
        hi = np.maximum(bodies["a"], bodies["b"]) + r
        centres, sizes, log_odds = self.tree.leaves(lo.min(axis=0), hi.max(axis=0))
        suspect = (log_odds > 0) & (sizes <= 1.01 * res)
        if not suspect.any():
            return 0
        centres = centres[suspect]
        # Voxel boxes that may overlap a body: centres within half a diagonal of it.
        touching = centres[~self.robot.self_filter(centres, q, 0.5 * np.sqrt(3) * res)]
        if len(touching):
            seen, _ = self.tree.current_obstacles()
            if len(seen):
                touching = touching[~np.isin(voxel_codes(touching, res), voxel_codes(seen, res))]
        # A few misses take a voxel from the clamp (log-odds 3.5) to free (< 0).
        for _ in range(10 if len(touching) else 0):
            self.tree.update_nodes(touching, occupied=False)
        return len(touching)

    def _close_frame(self, report: FrameReport, time_s: float) -> FrameReport:
        t7 = time.perf_counter()
        dt_frame = 1.0 / 15.0 if self._last_time is None else max(time_s - self._last_time, 1e-6)
        frame_report = self.tree.end_frame(dt_frame)
        self._last_time = time_s
        report.timings["end_frame"] = time.perf_counter() - t7
        report.danger_voxels = frame_report.active
        report.current_obstacles = frame_report.hit
        return report
