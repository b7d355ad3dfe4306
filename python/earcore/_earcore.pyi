"""Type stubs of the compiled extension (checked against it by mypy's stubtest)."""

from collections.abc import Sequence
from os import PathLike
from typing import Any, Literal, TypedDict, final, overload

from typing_extensions import disjoint_base

import numpy as np
import numpy.typing as npt

__all__ = [
    "__version__",
    "DANGER_ON_HIT",
    "OcTree",
    "SurfaceMap",
    "PlaneTarget",
    "IcpResult",
    "InsertReport",
    "FrameReport",
    "EarcoreError",
    "OutOfMapError",
    "MapFormatError",
    "set_num_threads",
    "get_num_threads",
    "set_local_num_threads",
    "voxel_codes",
    "voxel_means",
    "render_depth_points",
    "benchmark_frame",
    "render_lidar_scan",
    "depth_to_points_raw",
    "crop_raw",
    "statistical_outlier_indices",
    "voxel_downsample_raw",
    "estimate_normals",
    "cluster_points",
    "rigid_fit",
    "checked_rigid_transform",
    "rigid_fit_ransac",
    "icp_point_to_plane_raw",
    "RobotModel",
    "Follower",
    "Rasterizer",
    "PixelMap",
    "incidence_cosines",
    "fit_body",
    "robot_cell_voxels",
]

__version__: str
DANGER_ON_HIT: float

class EarcoreError(Exception): ...
class OutOfMapError(EarcoreError): ...
class MapFormatError(EarcoreError): ...

_ArrayLike = npt.ArrayLike
_F64 = npt.NDArray[np.float64]
_F32 = npt.NDArray[np.float32]

_DecayMode = Literal["observed", "always"]
_ObstacleSource = Literal["occupied", "current"]
_BodyShape = Literal["capsule", "cylinder"]
_JointKind = Literal["revolute", "continuous", "prismatic", "fixed"]

class _Bodies(TypedDict):
    """`RobotModel.bodies(q)`: the B padded bodies placed for one configuration."""

    link: npt.NDArray[np.int64]
    a: _F64
    b: _F64
    radius: _F64
    shape: list[_BodyShape]

class _Clearance(TypedDict):
    """`RobotModel.clearance` / `clearance_to_voxels`: scalars and (3,) points for one
    configuration (dof,), arrays (K,) and (K, 3) for a batch (K, dof). distance is inf
    and link -1 (points NaN) where there is no obstacle; negative when overlapping."""

    distance: float | _F64
    link: int | npt.NDArray[np.int64]
    on_robot: _F64
    on_obstacle: _F64

@final
class InsertReport:
    @property
    def rays(self) -> int: ...
    @property
    def free_cells(self) -> int: ...
    @property
    def occupied_cells(self) -> int: ...

@final
class FrameReport:
    @property
    def hit(self) -> int: ...
    @property
    def decayed(self) -> int: ...
    @property
    def cleared(self) -> int: ...
    @property
    def active(self) -> int: ...

@final
class OcTree:
    def __new__(
        cls,
        resolution: float = 0.05,
        *,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        clamping_min: float = 0.1192,
        clamping_max: float = 0.971,
        occupancy_threshold: float = 0.5,
        danger_alpha: float = 0.3,
        decay_mode: _DecayMode = "observed",
    ) -> OcTree: ...
    @property
    def resolution(self) -> float: ...
    @property
    def prob_hit(self) -> float: ...
    @property
    def prob_miss(self) -> float: ...
    @property
    def clamping_min(self) -> float: ...
    @property
    def clamping_max(self) -> float: ...
    @property
    def occupancy_threshold(self) -> float: ...
    @property
    def danger_alpha(self) -> float: ...
    @danger_alpha.setter
    def danger_alpha(self, alpha: float) -> None: ...
    @property
    def decay_mode(self) -> _DecayMode: ...
    @decay_mode.setter
    def decay_mode(self, mode: _DecayMode) -> None: ...
    def insert_point_cloud(
        self, points: _ArrayLike, sensor_origin: _ArrayLike, max_range: float | None = None, discretize: bool = False
    ) -> InsertReport: ...
    def is_occupied(self, points: _ArrayLike) -> npt.NDArray[np.int8]: ...
    def log_odds(self, points: _ArrayLike) -> _F32: ...
    def search(self, point: _ArrayLike, depth: int = 0) -> float | None: ...
    def insert_free_rays(self, points: _ArrayLike, sensor_origin: _ArrayLike, max_range: float | None = None) -> InsertReport: ...
    def update_node(self, point: _ArrayLike, update: bool | float) -> None: ...
    def update_nodes(self, points: _ArrayLike, occupied: bool = True) -> None: ...
    def set_log_odds(self, points: _ArrayLike, value: float) -> None: ...
    def update_log_odds(self, points: _ArrayLike, delta: float, *, repeat: int = 1) -> None: ...
    def leaves_at_full_depth(
        self, bbx_min: _ArrayLike, bbx_max: _ArrayLike, *, occupied_only: bool = False
    ) -> tuple[_F64, _F32]: ...
    def copy(self) -> OcTree: ...
    def __copy__(self) -> OcTree: ...
    def __deepcopy__(self, _memo: Any, /) -> OcTree: ...
    def occupied_voxels(self) -> tuple[_F64, _F64]: ...
    def leaves(self, bbx_min: _ArrayLike | None = None, bbx_max: _ArrayLike | None = None) -> tuple[_F64, _F64, _F32]: ...
    def leaf_keys(self) -> tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint8], _F32]: ...
    def cast_ray(
        self, origin: _ArrayLike, direction: _ArrayLike, max_range: float | None = None, ignore_unknown: bool = False
    ) -> tuple[bool, _F64]: ...
    def cast_rays(
        self, origins: _ArrayLike, directions: _ArrayLike, max_range: float | None = None, ignore_unknown: bool = False
    ) -> tuple[npt.NDArray[np.bool_], _F64]: ...
    def prune(self) -> None: ...
    def update_inner_occupancy(self) -> None: ...
    def size(self) -> int: ...
    def __len__(self) -> int: ...
    def num_leaf_nodes(self) -> int: ...
    def memory_usage(self) -> int: ...
    def clear(self) -> None: ...
    def write_binary(self, path: str | PathLike[str]) -> None: ...
    def write(self, path: str | PathLike[str]) -> None: ...
    @classmethod
    def read_binary(
        cls,
        path: str | PathLike[str],
        *,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        clamping_min: float = 0.1192,
        clamping_max: float = 0.971,
        occupancy_threshold: float = 0.5,
    ) -> OcTree: ...
    @classmethod
    def read(
        cls,
        path: str | PathLike[str],
        *,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        clamping_min: float = 0.1192,
        clamping_max: float = 0.971,
        occupancy_threshold: float = 0.5,
    ) -> OcTree: ...
    def end_frame(self, dt: float) -> FrameReport: ...
    def danger(self, points: _ArrayLike) -> _F32: ...
    def danger_voxels(self) -> tuple[_F64, _F64, _F32]: ...
    def current_obstacles(self) -> tuple[_F64, _F64]: ...

@final
class SurfaceMap:
    def __new__(
        cls,
        resolution: float = 0.01,
        *,
        prob_hit: float = 0.7,
        clamping_max: float = 0.971,
        similar: float = 0.25,
        position_memory: int | None = None,
    ) -> SurfaceMap: ...
    @property
    def resolution(self) -> float: ...
    def insert(
        self,
        points: _ArrayLike,
        sensor_origin: _ArrayLike | None = None,
        beam_spacing: float | None = None,
        max_leaf_size: float = 0.32,
    ) -> int: ...
    def nodes(
        self, depth: int | None = None, *, leaves_only: bool = False
    ) -> tuple[_F64, _F64, npt.NDArray[np.uint8]]: ...
    def associate(self, points: _ArrayLike) -> tuple[_F64, _F64, npt.NDArray[np.uint8]]: ...
    def size(self) -> int: ...
    def __len__(self) -> int: ...
    def memory_usage(self) -> int: ...

@final
class PlaneTarget:
    def __new__(cls, points: _ArrayLike, normals: _ArrayLike) -> PlaneTarget: ...
    def __len__(self) -> int: ...

@final
class Rasterizer:
    def __new__(cls, meshes: Sequence[tuple[_ArrayLike, _ArrayLike, _ArrayLike, int]]) -> Rasterizer: ...
    def __len__(self) -> int: ...
    def render(
        self,
        camera_from_mesh: _F64,
        hidden: Sequence[bool],
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        near: float,
        far: float,
        light: tuple[float, float, float],
        ambient: float,
        diffuse: float,
        background: tuple[int, int, int],
    ) -> tuple[npt.NDArray[np.uint8], _F64, npt.NDArray[np.int64]]: ...

@final
class PixelMap:
    def __new__(cls, source_width: int, source_height: int, u: _F64, v: _F64) -> PixelMap: ...
    def bilinear(self, image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]: ...
    def nearest(self, image: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]: ...
    def depth(self, depth: _F64, edge: float) -> _F64: ...

@final
class IcpResult:
    @property
    def transform(self) -> _F64: ...
    @property
    def rmse(self) -> float: ...
    @property
    def fitness(self) -> float: ...
    @property
    def iterations(self) -> int: ...
    @property
    def converged(self) -> bool: ...
    @property
    def degenerate(self) -> bool: ...
    @property
    def conditioning(self) -> float: ...

def icp_point_to_plane_raw(
    source: _ArrayLike,
    target: PlaneTarget | SurfaceMap,
    initial: _ArrayLike | None = None,
    *,
    max_iterations: int = 50,
    max_correspondence_distance: float = 0.2,
    translation_tolerance: float = 0.0,
    rotation_tolerance: float = 0.0,
    sigma_tolerance: float = 1.0,
    huber_delta: float | None = None,
    adaptive_huber: bool = False,
) -> IcpResult: ...
def set_num_threads(n: int) -> None: ...
def get_num_threads() -> int: ...
def set_local_num_threads(n: int | None) -> int | None: ...
def voxel_codes(points: _ArrayLike, resolution: float) -> npt.NDArray[np.int64]: ...
def voxel_means(centres: _ArrayLike, points: _ArrayLike, resolution: float) -> _F64: ...
def render_depth_points(
    base_from_camera: _ArrayLike,
    spheres: _ArrayLike,
    boxes: _ArrayLike,
    floor_z: float | None = None,
    *,
    width: int = 512,
    height: int = 424,
    fx: float = 365.0,
    fy: float = 365.0,
    cx: float = 256.0,
    cy: float = 212.0,
    max_depth: float = 4.5,
) -> _F64: ...
def benchmark_frame() -> tuple[_F64, _F64]: ...
def render_lidar_scan(
    base_from_sensor: _ArrayLike,
    spheres: _ArrayLike,
    boxes: _ArrayLike,
    floor_z: float | None = None,
    *,
    rings: int = 16,
    azimuth_steps: int = 940,
    vertical_fov_deg: float = 30.0,
    max_range: float = 100.0,
    noise_sigma: float = 0.015,
    seed: int = 0,
) -> _F64: ...
def incidence_cosines(depth: _F64, fx: float, fy: float) -> _F64: ...
def depth_to_points_raw(
    depth: _ArrayLike,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    distortion: _ArrayLike | None = None,
    depth_scale: float = 1.0,
    min_depth: float = 0.0,
    max_depth: float | None = None,
    base_from_camera: _ArrayLike | None = None,
) -> tuple[_F64, npt.NDArray[np.uint32]]: ...
def crop_raw(
    points: _ArrayLike,
    center: _ArrayLike | None = None,
    radius: float | None = None,
    box_min: _ArrayLike | None = None,
    box_max: _ArrayLike | None = None,
) -> tuple[_F64, npt.NDArray[np.uint32]]: ...
def statistical_outlier_indices(
    points: _ArrayLike, k: int = 20, std_ratio: float = 2.0
) -> tuple[npt.NDArray[np.uint32], _F64]: ...
def voxel_downsample_raw(points: _ArrayLike, voxel_size: float, values: _ArrayLike | None = None) -> tuple[_F64, _F64 | None]: ...
def estimate_normals(points: _ArrayLike, k: int = 20, viewpoint: _ArrayLike | None = None) -> tuple[_F64, _F64]: ...
def cluster_points(points: _ArrayLike, cell: float) -> npt.NDArray[np.uint32]: ...
def rigid_fit(src: _ArrayLike, dst: _ArrayLike, weights: _ArrayLike | None = None) -> _F64: ...
def checked_rigid_transform(matrix: _ArrayLike, name: str) -> _F64: ...
def rigid_fit_ransac(
    src: _ArrayLike, dst: _ArrayLike, threshold: float, iterations: int = 200, seed: int = 0
) -> tuple[_F64, npt.NDArray[np.bool_], float]: ...
def robot_cell_voxels(resolution: float = 0.05, seed: int = 0) -> _F64: ...

_BodySpec = tuple[tuple[float, float, float], tuple[float, float, float], float, _BodyShape]
_JointSpec = tuple[
    str,
    _JointKind,
    int,
    int,
    tuple[float, float, float],
    tuple[float, float, float],
    tuple[float, float, float],
    float,
    float,
]

@final
class Follower:
    def __new__(cls, max_velocity: _ArrayLike, max_acceleration: _ArrayLike, gain: float) -> Follower: ...
    def command(self, q: _ArrayLike, last: _ArrayLike, now: _ArrayLike | None, ahead: _ArrayLike | None, dt: float) -> _F64: ...
    def rollout(
        self,
        reference: _ArrayLike,
        q: _ArrayLike,
        command: _ArrayLike,
        dt: float,
        lower: _ArrayLike,
        upper: _ArrayLike,
        tolerance: float,
    ) -> tuple[_F64, bool, int, float]: ...

def fit_body(vertices: _ArrayLike, padding: float = 0.0, shape: Literal["capsule", "cylinder", "auto"] = "auto") -> _BodySpec: ...

@disjoint_base
class RobotModel:
    def __new__(
        cls,
        link_names: list[str],
        joints: list[_JointSpec],
        bodies: list[_BodySpec | None],
        *,
        name: str | None = None,
        padding: float = 0.0,
    ) -> RobotModel: ...
    @property
    def name(self) -> str: ...
    @property
    def padding(self) -> float: ...
    @property
    def dof(self) -> int: ...
    @property
    def link_names(self) -> list[str]: ...
    @property
    def joint_names(self) -> list[str]: ...
    @property
    def joint_limits(self) -> _F64: ...
    @property
    def base(self) -> _F64: ...
    @base.setter
    def base(self, value: _ArrayLike) -> None: ...
    @property
    def index_margin(self) -> float: ...
    @index_margin.setter
    def index_margin(self, value: float) -> None: ...
    @property
    def reach_bound(self) -> float: ...
    @property
    def fixed_to_root(self) -> list[bool]: ...
    @property
    def self_collision_pairs(self) -> list[tuple[int, int]]: ...
    @self_collision_pairs.setter
    def self_collision_pairs(self, value: list[tuple[int, int]]) -> None: ...
    @property
    def link_bodies(self) -> list[_BodySpec | None]: ...
    def fk(self, q: _ArrayLike) -> _F64: ...
    def jacobian(self, q: _ArrayLike, link: int, point: _ArrayLike) -> _F64: ...
    def frame_jacobian(self, q: _ArrayLike, link: int) -> _F64: ...
    def bodies(self, q: _ArrayLike) -> _Bodies: ...
    def self_filter(self, points: _ArrayLike, q: _ArrayLike, margin: float = 0.0) -> npt.NDArray[np.bool_]: ...
    @overload
    def check_configurations(
        self,
        tree: OcTree,
        qs: _ArrayLike,
        *,
        obstacles: _ObstacleSource = "occupied",
        self_collision: bool = True,
        return_links: Literal[False] = False,
    ) -> bool | npt.NDArray[np.bool_]: ...
    @overload
    def check_configurations(
        self,
        tree: OcTree,
        qs: _ArrayLike,
        *,
        obstacles: _ObstacleSource = "occupied",
        self_collision: bool = True,
        return_links: Literal[True],
    ) -> tuple[bool, int] | tuple[npt.NDArray[np.bool_], npt.NDArray[np.int32]]: ...
    @overload
    def check_configurations(
        self,
        tree: OcTree,
        qs: _ArrayLike,
        *,
        obstacles: _ObstacleSource = "occupied",
        self_collision: bool = True,
        return_links: bool,
    ) -> bool | npt.NDArray[np.bool_] | tuple[bool, int] | tuple[npt.NDArray[np.bool_], npt.NDArray[np.int32]]: ...
    def check_motion(
        self,
        tree: OcTree,
        q0: _ArrayLike,
        q1: _ArrayLike,
        resolution: float = 0.02,
        *,
        obstacles: _ObstacleSource = "occupied",
        self_collision: bool = True,
    ) -> bool: ...
    def check_motions(
        self,
        tree: OcTree,
        q0s: _ArrayLike,
        q1s: _ArrayLike,
        resolution: float = 0.02,
        *,
        obstacles: _ObstacleSource = "occupied",
        self_collision: bool = True,
    ) -> npt.NDArray[np.bool_]: ...
    def self_collisions(self, qs: _ArrayLike) -> npt.NDArray[np.bool_]: ...
    def clearance(self, tree: OcTree, qs: _ArrayLike, *, obstacles: _ObstacleSource = "occupied") -> _Clearance: ...
    def clearance_to_voxels(self, centres: _ArrayLike, size: float, qs: _ArrayLike) -> _Clearance: ...
    def touches_voxels(self, centres: _ArrayLike, size: float, qs: _ArrayLike) -> npt.NDArray[np.bool_]: ...
    def path_danger(self, tree: OcTree, path: _ArrayLike, resolution: float = 0.02) -> float: ...
    def motion_danger(self, tree: OcTree, q0: _ArrayLike, q1: _ArrayLike, resolution: float = 0.02) -> float: ...
