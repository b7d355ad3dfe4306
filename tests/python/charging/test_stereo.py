"""Stereo triangulation: exact on synthetic projections, against OpenCV's
triangulatePoints with noise, and Paper III's Eq. 1 against the exact geometry."""

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from earcore.charging.stereo import StereoRig, triangulate, verging_rig, verging_triangulation  # noqa: E402
from earcore.transforms import rotation_from_vector  # noqa: E402

K = np.array([[1400.0, 0.0, 639.5], [0.0, 1400.0, 479.5], [0.0, 0.0, 1.0]])


def random_points(rng, n=50):
    return np.c_[rng.uniform(-0.4, 0.4, (n, 2)), rng.uniform(1.5, 2.5, n)]


def test_rig_geometry():
    rig = verging_rig(K, 0.3, 8.0)
    assert rig.baseline == pytest.approx(0.3)
    assert rig.vergence_deg == pytest.approx(8.0)
    # the right camera's axis crosses the left one's at Z0 = b / tan(θ)
    z0 = 0.3 / np.tan(np.radians(8.0))
    _, right = rig.project(np.array([[0.0, 0.0, z0]]))
    assert right[0] == pytest.approx([639.5, 479.5], abs=1e-6)


def test_triangulation_is_exact_with_distortion_and_any_relative_pose():
    rng = np.random.default_rng(3)
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_vector([0.02, -0.15, 0.03])
    pose[:3, 3] = [-0.35, 0.02, 0.04]
    rig = StereoRig(K, K * [[1.02], [1.02], [1]], pose, np.array([-0.1, 0.05, 0.001, -0.001, 0.0]), np.array([0.08, -0.02, 0.0, 0.0, 0.0]))
    points = random_points(rng)
    left, right = rig.project(points)
    assert triangulate(rig, left, right) == pytest.approx(points, abs=1e-6)  # OpenCV undistorts iteratively


def test_triangulation_matches_opencv_with_noisy_pixels():
    rng = np.random.default_rng(4)
    rig = verging_rig(K, 0.3, 7.0)
    points = random_points(rng)
    left, right = rig.project(points)
    left, right = left + rng.normal(0, 0.5, left.shape), right + rng.normal(0, 0.5, right.shape)
    ours = triangulate(rig, left, right)
    p1, p2 = K @ np.eye(4)[:3], K @ rig.right_from_left[:3]
    x = cv2.triangulatePoints(p1, p2, left.T, right.T)
    theirs = (x[:3] / x[3]).T
    assert ours == pytest.approx(theirs, abs=1e-6)


def test_equation_1_is_exact_for_parallel_cameras_and_first_order_for_verging():
    rng = np.random.default_rng(5)
    points = random_points(rng)
    parallel = verging_rig(K, 0.3, 0.0)
    left, right = parallel.project(points)
    assert verging_triangulation(left, right, 1400.0, 0.3, 0.0, (639.5, 479.5)) == pytest.approx(points, abs=1e-9)
    theta = np.degrees(np.arctan(0.3 / 2.0))
    rig = verging_rig(K, 0.3, theta)
    on_axis = np.array([[0.0, 0.0, 2.0]])  # where the axes cross: exact
    assert verging_triangulation(*rig.project(on_axis), 1400.0, 0.3, theta, (639.5, 479.5)) == pytest.approx(on_axis, abs=1e-9)
    # elsewhere its error grows with the distance from Z0 and the point's angle off axis
    near = np.c_[rng.uniform(-0.05, 0.05, (20, 2)), rng.uniform(1.95, 2.05, 20)]
    far = np.c_[rng.uniform(-0.4, 0.4, (20, 2)), rng.uniform(1.5, 2.5, 20)]
    err_near = np.linalg.norm(verging_triangulation(*rig.project(near), 1400.0, 0.3, theta, (639.5, 479.5)) - near, axis=1)
    err_far = np.linalg.norm(verging_triangulation(*rig.project(far), 1400.0, 0.3, theta, (639.5, 479.5)) - far, axis=1)
    assert err_near.max() < err_far.max()
    assert err_far.max() > 1e-3  # an approximation, not the exact triangulation


def test_triangulation_refuses_mismatched_inputs():
    rig = verging_rig(K, 0.3, 7.0)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        triangulate(rig, np.zeros((3, 2)), np.zeros((4, 2)))
    assert triangulate(rig, np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 3)
