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
import math
import time
from dataclasses import dataclass, field

import numpy as np

import earcore
from earcore.cloud import box_voxel_centres, voxel_codes
from earcore.depth_error import DepthBias, radius2_grid
from earcore.interfaces import Frame
from earcore.perception.config import PerceptionConfig
from earcore.robots import RobotModel
from earcore.transforms import perturb_pose

__all__ = ["PerceptionPipeline", "PerceptionReport"]

STAGES = ("points", "crop", "voxel_grid", "outliers", "self_filter", "insert", "end_frame")


@dataclass
class PerceptionReport:
    """What one map frame did: per-stage timings and point counts."""

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


@dataclass
class CameraPoints:
    """One camera's contribution to a map frame, in the base frame."""

    #: Points to insert (cropped, above the table, voxel-grid centroids).
    points: np.ndarray
    #: The camera's position: where the points' rays start.
    origin: np.ndarray
    #: Per point, the fraction of it that was the tracked body (simulation; else 0).
    robot: np.ndarray
    #: The table's points and where far points' rays leave the crop sphere: free rays only.
    low: np.ndarray
    far: np.ndarray


@dataclass
class MergedCloud:
    """The cameras' points merged: per point, the camera whose ray it takes and the
    tracked body's fraction."""

    points: np.ndarray
    camera: np.ndarray
    robot: np.ndarray


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
        #: Per camera, the calibration its lens and pose came from (`load_calibration`).
        self._calibrated: dict = {}
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
        #: The points the last frame updated the map with (base frame).
        self.inserted_points: np.ndarray = np.zeros((0, 3))

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
            self._calibrated[name] = cam

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

    def frame_points(self, frame: Frame, **kwargs):
        """The frame's depth as points through the camera's calibrated lens (if set) with
        its calibrated depth error taken out; `kwargs` go to `earcore.depth_to_points`
        (e.g. `base_from_camera`, `return_pixels`)."""
        K, distortion = self.intrinsics.get(frame.camera, (frame.K, frame.distortion))
        calibrated = self._calibrated.get(frame.camera)
        if calibrated is not None:
            calibrated.check_image_size(frame.depth.shape[1], frame.depth.shape[0])
        return earcore.depth_to_points(
            self._depth_of(frame, K), K[0, 0], K[1, 1], K[0, 2], K[1, 2], distortion=distortion,
            max_depth=self.config.max_range, **kwargs,
        )

    def camera_pose(self, frame: Frame) -> np.ndarray:
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
        self.tree.set_log_odds(centres, math.inf)  # at the upper clamp: the table stays put
        return len(centres)

    def refine(self, frames: list[Frame]) -> None:
        """Paper II's one-off ICP refinement of the fixed cameras against each other."""
        fixed = [f for f in frames if self.fixed_cameras is None or f.camera in self.fixed_cameras]
        if len(fixed) < 2:
            return
        poses = [self.camera_pose(f) for f in fixed]
        origin = self.robot.base[:3, 3]
        clouds = []
        for f, pose in zip(fixed, poses):
            local = self.frame_points(f)
            # Only the working volume: the far floor and walls are planes that let
            # the alignment slide.
            in_base = local @ pose[:3, :3].T + pose[:3, 3]
            clouds.append(local[np.linalg.norm(in_base - origin, axis=1) <= self.config.crop_radius + 0.5])
        refined = earcore.refine_camera_poses(clouds, poses, max_correspondence_distance=0.08)
        for f, pose in zip(fixed, refined):
            self.poses[f.camera] = pose

    def process(self, frames: list[Frame], q: np.ndarray, time_s: float) -> PerceptionReport:
        """Integrate the frames captured at `time_s` with the robot at joint state `q`:
        Paper II's Fig. 1, one method per stage."""
        report = PerceptionReport(time_s, {s: 0.0 for s in STAGES})
        if not self._refined and frames:
            self.refine(frames)
            self._refined = True
        views = [self.camera_points(frame, report) for frame in frames]
        if not sum(len(v.points) for v in views):
            self.inserted_points = np.zeros((0, 3))
            self.insert(None, views, report)
            return self.end_frame(report, time_s)
        cloud = self.merge(views, report)
        cloud = self.remove_outliers(cloud, report)
        cloud = self.remove_robot(cloud, q, report)
        self.inserted_points = cloud.points
        self.insert(cloud, views, report)
        report = self.end_frame(report, time_s)
        t0 = time.perf_counter()
        self._clear_robot_volume(q)
        report.timings["self_filter"] += time.perf_counter() - t0
        return report

    def camera_points(self, frame: Frame, report: PerceptionReport) -> CameraPoints:
        """One camera's frame as points in the base frame (stage "points"), cropped
        around the robot, the table's points and the far points' rays set aside to
        clear space (stage "crop"), and a first voxel grid that shrinks the merge
        (stage "voxel_grid")."""
        c = self.config
        origin = self.robot.base[:3, 3]
        t0 = time.perf_counter()
        pose = self.camera_pose(frame)
        pts, pixels = self.frame_points(frame, base_from_camera=pose, return_pixels=True)
        report.points_in += len(pts)
        t1 = time.perf_counter()
        all_pts = pts
        pts, idx = earcore.crop(pts, center=origin, radius=c.crop_radius, return_index=True)
        far = np.zeros((0, 3))
        if c.clear_beyond_crop and len(idx) < len(all_pts):
            # About FAR_RAYS_ACROSS rays across the image are plenty (they are thinned to
            # one per map cell where they leave the sphere anyway) and keep this cheap:
            # at full resolution the far points are most of a Kinect's frame.
            on_grid = np.flatnonzero(_pixel_grid(frame.depth.shape)[pixels])
            beyond = on_grid[~_in_sorted(idx, on_grid)]
            far = _cut_at_sphere(all_pts.take(beyond, axis=0), pose[:3, 3], origin, c.crop_radius)
        low = np.zeros((0, 3))
        if c.min_height is not None:
            # Low points (the table) only clear the space in front of them.
            above = pts[:, 2] >= c.min_height
            low = np.compress(~above, pts, axis=0)
            pts, idx = np.compress(above, pts, axis=0), idx[above]
        robot = np.zeros(len(pts))
        tracking = self.track_body is not None
        if tracking and frame.segmentation is not None:
            robot = (frame.segmentation.reshape(-1)[pixels[idx]] == self.track_body).astype(np.float64)
        t2 = time.perf_counter()
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
        return CameraPoints(pts, pose[:3, 3], robot, low, far)

    def merge(self, views: list[CameraPoints], report: PerceptionReport) -> MergedCloud:
        """The cameras' clouds merged by one voxel grid (stage "voxel_grid"); each
        centroid remembers which camera contributed most of its points (its ray is cast
        from there) and, in simulation, the fraction of them that were the tracked body's."""
        c = self.config
        n_cam = len(views)
        merged = np.vstack([v.points for v in views])
        values = np.zeros((len(merged), n_cam + 1))
        start = 0
        for i, v in enumerate(views):
            values[start : start + len(v.points), i] = 1.0
            values[start : start + len(v.points), n_cam] = v.robot
            start += len(v.points)
        t0 = time.perf_counter()
        if c.voxel_size > 0:
            pts, means = earcore.voxel_downsample(merged, c.voxel_size, values)
        else:
            pts, means = merged, values
        report.timings["voxel_grid"] += time.perf_counter() - t0
        return MergedCloud(pts, np.argmax(means[:, :n_cam], axis=1), means[:, n_cam])

    def remove_outliers(self, cloud: MergedCloud, report: PerceptionReport) -> MergedCloud:
        """Statistical outlier removal (stage "outliers")."""
        c = self.config
        t0 = time.perf_counter()
        if len(cloud.points) > c.outlier_k:
            pts, idx = earcore.remove_statistical_outliers(cloud.points, c.outlier_k, c.outlier_std_ratio, return_index=True)
            cloud = MergedCloud(pts, cloud.camera[idx], cloud.robot[idx])
        report.timings["outliers"] += time.perf_counter() - t0
        return cloud

    def remove_robot(self, cloud: MergedCloud, q: np.ndarray, report: PerceptionReport) -> MergedCloud:
        """The self-filter at joint state `q` (stage "self_filter"): points inside the
        robot's padded bodies, grown by `self_filter_margin`, are dropped."""
        t0 = time.perf_counter()
        keep = self.robot.self_filter(cloud.points, q, self.config.self_filter_margin)
        report.removed_as_robot += int((~keep).sum())
        if self.track_body is not None:
            tracked = cloud.robot > 0.5
            report.tracked_points += int(tracked.sum())
            report.tracked_inserted += int((tracked & keep).sum())
        out = MergedCloud(np.compress(keep, cloud.points, axis=0), cloud.camera[keep], cloud.robot[keep])
        report.timings["self_filter"] += time.perf_counter() - t0
        return out

    def insert(self, cloud: MergedCloud | None, views: list[CameraPoints], report: PerceptionReport) -> None:
        """Octree insertion (stage "insert"): the free rays first (to the table's points
        and out of the crop sphere), then each point's ray from the camera that saw it."""
        t0 = time.perf_counter()
        self._insert_free_rays([v.origin for v in views], [v.low for v in views], [v.far for v in views])
        if cloud is not None:
            for i, view in enumerate(views):
                mine = np.compress(cloud.camera == i, cloud.points, axis=0)
                if len(mine):
                    self.tree.insert_point_cloud(mine, view.origin, max_range=self.config.max_range)
                    report.points_inserted += len(mine)
        report.timings["insert"] += time.perf_counter() - t0

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
        # Ten misses take a voxel from the clamp (log-odds 3.5) to free (< 0).
        if len(touching):
            miss = math.log(self.tree.prob_miss / (1 - self.tree.prob_miss))
            self.tree.update_log_odds(touching, miss, repeat=10)
        return len(touching)

    def end_frame(self, report: PerceptionReport, time_s: float) -> PerceptionReport:
        """End of frame (stage "end_frame"): the danger of every voxel not hit decays
        by the time since the last frame (Eq. 1)."""
        t7 = time.perf_counter()
        dt_frame = 1.0 / 15.0 if self._last_time is None else max(time_s - self._last_time, 1e-6)
        frame_report = self.tree.end_frame(dt_frame)
        self._last_time = time_s
        report.timings["end_frame"] = time.perf_counter() - t7
        report.danger_voxels = frame_report.active
        report.current_obstacles = frame_report.hit
        return report
