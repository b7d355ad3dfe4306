"""earcore: an environment-aware robot arm toolkit.

The map core is :class:`OcTree`, an occupancy octree with OctoMap's semantics and
file formats plus a per-voxel danger value that decays as in Paper II (Eq. 1).
Heavy numeric work runs in Rust (``earcore._earcore``) without holding the GIL.
"""

from __future__ import annotations

try:
    from earcore._earcore import (
        DANGER_ON_HIT,
        EarcoreError,
        FrameReport,
        InsertReport,
        MapFormatError,
        OcTree,
        OutOfMapError,
        SurfaceMap,
        __version__,
        fit_body,
    )
except ImportError as exc:  # pragma: no cover - exercised by `earcore --version` on a broken install
    raise ImportError(
        "earcore's compiled extension (earcore._earcore) failed to load: "
        f"{exc}. Reinstall the wheel (`pip install --force-reinstall earcore`) or rebuild with `make develop`."
    ) from exc

from earcore import errors, interfaces, robots, synthetic, transforms  # noqa: E402  (light: numpy and the extension only)
from earcore.cloud import (  # noqa: E402
    cluster_points,
    crop,
    depth_to_points,
    estimate_normals,
    remove_statistical_outliers,
    voxel_downsample,
)
from earcore.lidar_odometry import LidarOdometry, OdometrySettings  # noqa: E402
from earcore.parallel import get_num_threads, set_num_threads, threads  # noqa: E402
from earcore.registration import (  # noqa: E402
    DegenerateAlignmentWarning,
    IcpResult,
    PlaneTarget,
    icp_point_to_plane,
    refine_camera_poses,
    rigid_fit,
    rigid_fit_ransac,
)
from earcore.robots import RobotModel  # noqa: E402

__all__ = [
    "DANGER_ON_HIT",
    "DegenerateAlignmentWarning",
    "EarcoreError",
    "IcpResult",
    "PlaneTarget",
    "icp_point_to_plane",
    "refine_camera_poses",
    "rigid_fit",
    "rigid_fit_ransac",
    "cluster_points",
    "crop",
    "depth_to_points",
    "estimate_normals",
    "remove_statistical_outliers",
    "voxel_downsample",
    "FrameReport",
    "InsertReport",
    "MapFormatError",
    "OcTree",
    "OutOfMapError",
    "RobotModel",
    "SurfaceMap",
    "LidarOdometry",
    "OdometrySettings",
    "fit_body",
    "errors",
    "interfaces",
    "robots",
    "transforms",
    "__version__",
    "get_num_threads",
    "set_num_threads",
    "threads",
    "synthetic",
]
