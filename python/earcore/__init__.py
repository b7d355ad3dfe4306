"""earcore: an environment-aware robot arm toolkit.

The map core is :class:`OcTree`, an occupancy octree with OctoMap's semantics and
file formats plus a per-voxel danger value that decays as in Paper II (Eq. 1).
Heavy numeric work runs in Rust (``earcore._earcore``) without holding the GIL.
"""

from __future__ import annotations

#: Submodules named in __all__ (importable without the core's names).
_SUBMODULES = {"errors", "interfaces", "robots", "synthetic", "transforms"}
_CORE_HINT = "Reinstall the wheel (`pip install --force-reinstall earcore`) or rebuild with `make develop`."

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
except ImportError as _core_error:
    # Without the compiled core, the pure-Python parts (earcore.learning and the pose
    # networks' training, e.g. on a GPU machine with another Python) still import;
    # anything that needs the core raises this on first use.
    _CORE_MISSING = ImportError(f"earcore's compiled extension (earcore._earcore) failed to load: {_core_error}. {_CORE_HINT}")

    def __getattr__(name: str):
        # Only the core's names raise; anything else (a submodule asked for by
        # `from earcore import validate`, a probe like __wrapped__) stays an AttributeError,
        # so the import system goes on to load the submodule.
        if name == "__version__" or (name in __all__ and name not in _SUBMODULES):
            raise _CORE_MISSING
        raise AttributeError(f"module 'earcore' has no attribute {name!r}")
else:
    from earcore import errors, interfaces, robots, synthetic, transforms  # light: numpy and the extension only
    from earcore.cloud import (
        cluster_points,
        crop,
        depth_to_points,
        estimate_normals,
        remove_statistical_outliers,
        voxel_downsample,
    )
    from earcore.lidar_odometry import LidarOdometry, OdometrySettings
    from earcore.parallel import get_num_threads, set_num_threads, threads
    from earcore.registration import (
        DegenerateAlignmentWarning,
        IcpResult,
        PlaneTarget,
        icp_point_to_plane,
        refine_camera_poses,
        rigid_fit,
        rigid_fit_ransac,
    )
    from earcore.robots import RobotModel

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
