"""Bad input gets a clear exception, never a crash, and leaves the tree as it was."""

from __future__ import annotations

import numpy as np
import pytest

import earcore


@pytest.fixture
def tree():
    t = earcore.OcTree(0.05)
    rng = np.random.default_rng(0)
    t.insert_point_cloud(rng.uniform(-1, 1, (500, 3)) + [0, 0, 2], [0, 0, 0])
    t.end_frame(0.1)
    return t


def snapshot(tree, tmp_path):
    path = tmp_path / "snap.ot"
    tree.write(path)
    return path.read_bytes(), tree.danger_voxels()[2].tobytes()


GOOD = np.array([[1.0, 0.5, 0.2]])


@pytest.mark.parametrize(
    "points, error, message",
    [
        (np.array([[np.nan, 0, 0]]), ValueError, "not finite"),
        (np.array([[0, np.inf, 0]]), ValueError, "not finite"),
        (np.vstack([GOOD, [[0, 0, -np.inf]]]), ValueError, "point 1"),
        (np.zeros(3), ValueError, r"\(N, 3\)"),
        (np.zeros((4, 2)), ValueError, r"\(N, 3\)"),
        (np.zeros((2, 3, 1)), ValueError, r"\(N, 3\)"),
        (np.array([["a", "b", "c"]]), TypeError, "numbers"),
        (np.zeros((0, 3)), ValueError, "empty"),
        (np.array([[5000.0, 0, 0]]), earcore.OutOfMapError, "outside the map"),
        (np.array([[0, 0, -1638.41]]), earcore.OutOfMapError, "outside the map"),
    ],
)
def test_bad_points_raise_and_change_nothing(tree, tmp_path, points, error, message):
    before = snapshot(tree, tmp_path)
    with pytest.raises(error, match=message):
        tree.insert_point_cloud(points, [0, 0, 0])
    assert snapshot(tree, tmp_path) == before


@pytest.mark.parametrize(
    "kwargs, error",
    [
        (dict(sensor_origin=[np.nan, 0, 0]), ValueError),
        (dict(sensor_origin=[0, 0]), ValueError),
        (dict(sensor_origin=[1e6, 0, 0]), earcore.OutOfMapError),
        (dict(sensor_origin=[0, 0, 0], max_range=0.0), ValueError),
        (dict(sensor_origin=[0, 0, 0], max_range=-2.0), ValueError),
        (dict(sensor_origin=[0, 0, 0], max_range=float("nan")), ValueError),
    ],
)
def test_bad_scan_arguments(tree, tmp_path, kwargs, error):
    before = snapshot(tree, tmp_path)
    with pytest.raises(error):
        tree.insert_point_cloud(GOOD, **kwargs)
    assert snapshot(tree, tmp_path) == before


@pytest.mark.parametrize("resolution", [0.0, -0.05, float("nan"), float("inf")])
def test_bad_resolution(resolution):
    with pytest.raises(ValueError, match="resolution"):
        earcore.OcTree(resolution)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(prob_hit=1.0), dict(prob_miss=0.0), dict(prob_hit=0.3), dict(prob_miss=0.7),
        dict(clamping_min=0.9, clamping_max=0.2), dict(danger_alpha=-1.0), dict(decay_mode="sometimes"),
    ],
)
def test_bad_parameters(kwargs):
    with pytest.raises(ValueError):
        earcore.OcTree(0.05, **kwargs)


def test_other_calls_reject_bad_input(tree, tmp_path):
    before = snapshot(tree, tmp_path)
    with pytest.raises(ValueError):
        tree.cast_ray([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        tree.cast_ray([0, 0, 0], [np.nan, 1, 0])
    with pytest.raises(earcore.OutOfMapError):
        tree.cast_ray([1e5, 0, 0], [1, 0, 0])
    with pytest.raises(ValueError):
        tree.cast_rays(np.zeros((3, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError):
        tree.end_frame(-0.1)
    with pytest.raises(ValueError):
        tree.end_frame(float("nan"))
    with pytest.raises(earcore.OutOfMapError):
        tree.update_node([1e5, 0, 0], True)
    with pytest.raises(ValueError):
        tree.update_node([0, 0, 0], float("nan"))
    with pytest.raises(TypeError):
        tree.update_node([0, 0, 0], "hit")
    with pytest.raises(ValueError):
        tree.is_occupied(np.zeros((5, 4)))
    with pytest.raises(earcore.OutOfMapError):
        tree.search([0, 0, 1e9])
    with pytest.raises(ValueError):
        tree.danger_alpha = float("inf")
    assert snapshot(tree, tmp_path) == before


def test_queries_accept_any_numeric_array_and_off_map_points(tree):
    pts = np.array([[0, 0, 2]], dtype=np.float32)
    assert tree.is_occupied(pts).dtype == np.int8
    assert tree.is_occupied([[0, 0, 2]]).shape == (1,)
    assert tree.is_occupied(np.asfortranarray(np.zeros((4, 3)))).shape == (4,)
    # Points off the map are simply unknown (and never dangerous) for queries.
    far = np.array([[1e7, 0, 0], [np.nan, 0, 0]])
    assert list(tree.is_occupied(far)) == [-1, -1]
    assert np.isnan(tree.log_odds(far)).all()
    assert list(tree.danger(far)) == [0.0, 0.0]
    assert tree.is_occupied(np.zeros((0, 3))).shape == (0,)


def test_exceptions_are_earcore_errors():
    assert issubclass(earcore.OutOfMapError, earcore.EarcoreError)
    assert issubclass(earcore.MapFormatError, earcore.EarcoreError)


def test_every_exception_the_package_defines_is_an_earcore_error():
    """One hierarchy: every exception class any earcore module defines (warnings aside)
    derives from `EarcoreError`, found by importing every module of the package."""
    import importlib
    import inspect
    import pkgutil

    defined = {}
    for info in pkgutil.walk_packages(earcore.__path__, "earcore."):
        if info.name.endswith("__main__"):
            continue
        try:
            module = importlib.import_module(info.name)
        except ImportError:  # an optional dependency (OMPL, OpenCV, pybullet) is missing
            continue
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__.startswith("earcore"):
                defined[f"{cls.__module__}.{cls.__qualname__}"] = cls
    assert "earcore.calibration.errors.CalibrationError" in defined and "earcore.planning.errors.PlanningError" in defined
    stray = [name for name, cls in defined.items() if not issubclass(cls, (earcore.EarcoreError, Warning))]
    assert not stray, stray


# --- A sweep of every public call with bad arguments ------------------------------


def _toy_arm():
    """Two links on revolute joints; an occupied cell above the base that the arm
    sweeps through between q = (0, -1.5) and (0, 1.5) but touches at neither end."""
    robot = earcore.RobotModel(
        ["a", "b", "c"],
        [("j0", "revolute", 0, 1, (0, 0, 0.1), (0, 0, 0), (0, 0, 1.0), -3.0, 3.0),
         ("j1", "revolute", 1, 2, (0, 0, 0.3), (0, 0, 0), (0, 1.0, 0), -2.0, 2.0)],
        [None, ((0, 0, 0.0), (0, 0, 0.3), 0.05, "capsule"), ((0, 0, 0.0), (0, 0, 0.3), 0.05, "capsule")],
    )
    tree = earcore.OcTree(0.05)
    tree.update_nodes([[0, 0, 0.62]], True)
    return robot, tree


@pytest.mark.parametrize("resolution", [1e-9, 1e-100, 1e-300])
def test_motion_resolution_too_fine_is_an_error_not_a_skip(resolution):
    robot, tree = _toy_arm()
    a, b = [0.0, -1.5], [0.0, 1.5]
    assert robot.check_motion(tree, a, b, 0.02)  # the middle collides (reference answer)
    tree.end_frame(0.1)
    for call in (lambda: robot.check_motion(tree, a, b, resolution),
                 lambda: robot.check_motions(tree, [a], [b], resolution),
                 lambda: robot.motion_danger(tree, a, b, resolution),
                 lambda: robot.path_danger(tree, [a, b], resolution)):
        with pytest.raises(ValueError, match="coarser resolution"):
            call()


def test_path_danger_checks_a_lone_configuration():
    robot, tree = _toy_arm()
    with pytest.raises(ValueError):
        robot.path_danger(tree, [0.0, np.nan])
    assert robot.path_danger(tree, [0.0, 0.5]) == 0.0  # one configuration: no motion


@pytest.mark.parametrize("n", [-1, 100_000])
def test_thread_count_is_bounded(n):
    before = earcore.get_num_threads()
    with pytest.raises(ValueError, match="num_threads"):
        earcore.set_num_threads(n)
    assert earcore.get_num_threads() == before


@pytest.mark.parametrize("depth", [-1, 17, 1000])
def test_search_depth_beyond_the_tree_is_an_error(tree, depth):
    with pytest.raises(ValueError, match="depth"):
        tree.search([0, 0, 2], depth=depth)
    tree.search([0, 0, 2], depth=16)


def test_cells_too_small_to_tell_points_apart_are_an_error():
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    for call in (lambda: earcore.cloud.voxel_downsample(pts, 1e-300),
                 lambda: earcore.cloud.cluster_points(pts, 1e-20),
                 lambda: earcore.cloud.cluster_points(pts * 1e300, 1.0),
                 lambda: earcore.cloud.voxel_codes(pts, 1e-12),
                 lambda: earcore.cloud.voxel_codes(pts, 0.0),
                 lambda: earcore.cloud.voxel_codes([[np.nan, 0, 0]], 0.05),
                 lambda: earcore.cloud.voxel_means(pts, pts, 0.0),
                 lambda: earcore.cloud.voxel_means([[np.inf, 0, 0]], pts, 0.05),
                 lambda: earcore.cloud.voxel_means(pts, [[np.nan, 0, 0]], 0.05)):
        with pytest.raises(ValueError):
            call()
    # Reasonable cells still tell every point apart.
    assert len(earcore.cloud.voxel_downsample(pts, 1e-9)) == 50
    assert len(set(earcore.cloud.cluster_points(pts, 1e-9))) == 50


@pytest.mark.parametrize("kwargs", [dict(control_period=0.0), dict(control_period=float("nan")),
                                    dict(control_period=-0.1), dict(initial_speed=float("nan")),
                                    dict(step=0.0), dict(max_acceleration=float("inf"))])
def test_time_parameterize_rejects_bad_timing(kwargs):
    from earcore.planning.trajectory import time_parameterize

    args = dict(max_velocity=1.0, max_acceleration=2.0) | kwargs
    with pytest.raises(ValueError):
        time_parameterize([[0.0, 0.0], [1.0, 0.5]], args.pop("max_velocity"), args.pop("max_acceleration"), **args)


def test_depth_to_points_drops_infinite_readings_and_rejects_nan_lenses():
    depth = np.full((4, 4), 1.0)
    depth[1, 2] = np.inf
    depth[2, 1] = -np.inf
    pts = earcore.cloud.depth_to_points(depth, 300.0, 300.0, 2.0, 2.0)
    assert len(pts) == 14 and np.isfinite(pts).all()
    with pytest.raises(ValueError, match="distortion"):
        earcore.cloud.depth_to_points(depth, 300.0, 300.0, 2.0, 2.0, distortion=[np.nan, 0, 0, 0])


def test_rigid_fits_reject_what_would_come_out_nan():
    p = np.random.default_rng(1).uniform(-1, 1, (20, 3))
    far = np.r_[p[:-1], [[1e300, 0, 0]]]
    with pytest.raises(ValueError, match="too large"):
        earcore.rigid_fit(p, far)
    with pytest.raises(ValueError, match="threshold"):
        earcore.rigid_fit_ransac(p, p, 1e-300)


@pytest.mark.parametrize("kwargs", [dict(huber_delta=float("nan")), dict(huber_delta=-1.0), dict(huber_delta=0.0),
                                    dict(translation_tolerance=float("nan")), dict(max_correspondence_distance=float("inf"))])
def test_icp_rejects_bad_parameters(kwargs):
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 20), np.linspace(-1, 1, 20), [0.0]), -1).reshape(-1, 3)
    target = earcore.PlaneTarget(g, np.tile([0, 0, 1.0], (len(g), 1)))
    with pytest.raises(ValueError, match="ICP"):
        earcore._earcore.icp_point_to_plane_raw(g + [0, 0, 0.01], target, **kwargs)


def test_robot_model_rejects_non_finite_origins_and_padding():
    def arm(xyz=(0, 0, 0.1), rpy=(0, 0, 0), padding=0.0):
        return earcore.RobotModel(["a", "b"], [("j0", "revolute", 0, 1, xyz, rpy, (0, 0, 1.0), -3.0, 3.0)],
                                  [None, ((0, 0, 0.0), (0, 0, 0.3), 0.05, "capsule")], padding=padding)

    arm()
    for kwargs in (dict(xyz=(0, np.nan, 0.1)), dict(rpy=(np.inf, 0, 0)), dict(padding=float("nan")), dict(padding=-1.0)):
        with pytest.raises(ValueError):
            arm(**kwargs)


def test_synthetic_scenes_check_their_tables_and_take_any_pose_dtype():
    from earcore import _earcore

    spheres = [[0, 0, 2.0, 0.3]]
    reference = _earcore.render_depth_points(np.eye(4), spheres, np.zeros((0, 6)), width=32, height=24, fx=30, fy=30, cx=16, cy=12)
    same = _earcore.render_depth_points(np.eye(4, dtype=np.float32), spheres, [], width=32, height=24, fx=30, fy=30, cx=16, cy=12)
    assert len(reference) > 0 and np.array_equal(reference, same)
    for bad in (np.zeros((4, 3)), [[0, 0, 2.0, np.nan]], [[0, 0, 2.0, -0.3]]):
        with pytest.raises(ValueError, match="sphere"):
            _earcore.render_depth_points(np.eye(4), bad, [], width=32, height=24, fx=30, fy=30, cx=16, cy=12)
    with pytest.raises(ValueError, match="box"):
        _earcore.render_depth_points(np.eye(4), [], [[1, 1, 1, 0, 0, 0]], width=32, height=24, fx=30, fy=30, cx=16, cy=12)


def test_index_arguments_name_what_they_index():
    robot, _ = _toy_arm()
    from earcore.planning.ik import solve_ik
    from earcore.registration import refine_camera_poses

    with pytest.raises(ValueError, match="link"):
        solve_ik(robot, np.eye(4), link=99)
    cloud = np.random.default_rng(2).uniform(-1, 1, (100, 3))
    with pytest.raises(ValueError, match="reference"):
        refine_camera_poses([cloud, cloud], [np.eye(4), np.eye(4)], reference=5)


def test_follower_limits_must_be_intervals_and_odometry_poses_rigid():
    from earcore.lidar_odometry import LidarOdometry
    from earcore.planning.follower import Follower
    from earcore.planning.trajectory import time_parameterize

    motion = time_parameterize([[0.0], [1.0]], 1.0, 2.0)
    with pytest.raises(ValueError, match="interval"):
        Follower(np.ones(1), np.ones(1)).rollout(motion, np.zeros(1), np.zeros(1), 1 / 30, np.array([[1.0, -1.0]]))
    with pytest.raises(ValueError, match="rigid"):
        LidarOdometry(initial_pose=np.diag([2.0, 2.0, 2.0, 1.0]))


def test_a_point_closer_than_float_can_measure_but_across_a_border_does_not_hang():
    """An end 3e-45 m from an origin on a cell border: its float length is 0 and its
    direction infinite, and OctoMap's ray walk never ends on it. earcore visits the
    origin cell alone (the end cell is hit as usual). Run in a child process, so that a
    regression fails instead of hanging the suite."""
    import subprocess
    import sys

    script = (
        "import numpy as np, earcore\n"
        "t = earcore.OcTree(0.05)\n"
        "pts = np.array([[0.0, -3e-45, 3e-45], [-3e-45, -3e-45, 3e-45]])\n"
        "r = t.insert_point_cloud(pts, [0.0, 0.0, 0.0])\n"
        "print(r.free_cells, r.occupied_cells)\n"
        "print(*t.is_occupied(np.array([[0.01, 0.01, 0.01], [0.01, -0.01, 0.01], [-0.01, -0.01, 0.01]])))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)
    counts, occupancy = out.stdout.split("\n")[:2]
    assert counts == "1 2"  # the origin cell free, both end cells hit
    assert occupancy == "0 1 1"
