"""Kinematic refinement recovers a UR5's joint angles and base pose from its keypoints;
PnP recovers the base pose when the joint angles are known."""

from __future__ import annotations

import numpy as np
import pytest

robots = pytest.importorskip("earcore.robots")

from earcore.pose.refine import keypoint_links, pnp_base, refine  # noqa: E402

K = np.array([[365.0, 0, 255.5], [0, 365.0, 211.5], [0, 0, 1]])
#: the dataset's keypoints: the actuated joints' frames in chain order, then the flange
NAMES = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint", "tool0"]


@pytest.fixture(scope="module")
def ur5():
    try:
        return robots.load("ur5")
    except ImportError as exc:
        pytest.skip(str(exc))


def scene(robot, q):
    """camera_from_base looking at the robot from 2 m, and the keypoints in the camera frame."""
    angle = np.radians(35)
    eye = np.array([2.0 * np.cos(angle), 2.0 * np.sin(angle), 0.9])
    target = np.array([0.0, 0.0, 0.4])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    base_from_camera = np.eye(4)
    base_from_camera[:3, :3] = np.stack([x, y, z], 1)
    base_from_camera[:3, 3] = eye
    pose = np.linalg.inv(base_from_camera)
    links = keypoint_links(robot, NAMES)
    frames = robot.fk(q)
    points = frames[links, :3, 3] @ pose[:3, :3].T + pose[:3, 3]
    return pose, points


def project(points):
    return np.stack([K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2], K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]], 1)


def test_keypoint_names_resolve_to_the_joints_child_links(ur5):
    links = keypoint_links(ur5, NAMES)
    assert [ur5.link_names[i] for i in links] == ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link", "tool0"]
    with pytest.raises(ValueError, match="neither a link"):
        keypoint_links(ur5, ["elbow"])


Q = np.array([0.4, -1.1, 1.3, -0.9, 1.2, 0.3])
#: what keypoints at joint origins can show: not the last joint (tool0 lies on its axis),
#: and the first only together with the base's rotation about it
SEEN = slice(1, 5)


def test_noiseless_keypoints_give_the_joint_angles_and_base(ur5):
    pose, points = scene(ur5, Q)
    fit = refine(ur5, points, names=NAMES, base=pose[:3, 3])
    assert np.abs(fit.keypoints - points).max() < 1e-6
    assert np.abs(fit.joints[SEEN] - Q[SEEN]).max() < 1e-5
    assert np.linalg.norm(fit.base - pose[:3, 3]) < 1e-6
    # the fitted base frame differs from the truth only by a rotation about its z axis
    relative = np.linalg.inv(pose) @ fit.camera_from_base
    assert np.abs(relative[:3, 2] - [0, 0, 1]).max() < 1e-6


def test_pixels_fix_the_depth_the_network_gets_wrong(ur5):
    pose, points = scene(ur5, Q)
    rng = np.random.default_rng(3)
    pixels = project(points) + rng.normal(0, 1.0, (len(points), 2))
    # the network's depth: 10 cm wrong on average, as a pilot found
    noisy = points.copy()
    noisy[:, 2] += rng.normal(0, 0.1, len(points))
    fit = refine(ur5, noisy, names=NAMES, pixels=pixels, intrinsics=K, base=pose[:3, 3] + rng.normal(0, 0.05, 3))
    before = np.linalg.norm(noisy - points, axis=1).mean()
    after = np.linalg.norm(fit.keypoints - points, axis=1).mean()
    assert after < 0.03 and after < before / 2, (before, after)
    assert np.abs(fit.joints[SEEN] - Q[SEEN]).max() < np.radians(6)


def test_noisy_3d_keypoints(ur5):
    pose, points = scene(ur5, Q)
    rng = np.random.default_rng(4)
    noisy = points + rng.normal(0, 0.01, points.shape)
    fit = refine(ur5, noisy, names=NAMES, base=pose[:3, 3] + rng.normal(0, 0.01, 3))
    assert np.linalg.norm(fit.keypoints - points, axis=1).mean() < 0.012
    # 1 cm of noise on levers of 8-9 cm (shoulder above the base, wrist 2 to tool0) is ~7° each
    assert np.abs(fit.joints[SEEN] - Q[SEEN]).max() < np.radians(15)
    # without the base, its tilt about the shoulder trades against the shoulder angle: the keypoints still fit
    free = refine(ur5, noisy, names=NAMES)
    assert np.linalg.norm(free.keypoints - points, axis=1).mean() < 0.012


def test_joint_limits_are_kept(ur5):
    limits = np.clip(ur5.joint_limits, -np.pi, np.pi)
    pose, points = scene(ur5, Q)
    fit = refine(ur5, points * 1.3, names=NAMES)  # a robot 30 % too large: no exact fit
    assert np.all(fit.joints >= limits[:, 0]) and np.all(fit.joints <= limits[:, 1])


def test_pnp_recovers_the_base_pose(ur5):
    pytest.importorskip("cv2")
    pose, points = scene(ur5, Q)
    found = pnp_base(ur5, Q, project(points), K, names=NAMES)
    assert np.abs(found - pose).max() < 1e-6
    with pytest.raises(ValueError, match="at least 4"):
        pnp_base(ur5, Q, project(points)[:3], K, names=NAMES[:3])


def test_pnp_leaves_out_a_misplaced_keypoint_and_uses_the_base(ur5):
    pytest.importorskip("cv2")
    pose, points = scene(ur5, Q)
    uv = project(points)
    base_uv = project(pose[:3, 3][None])[0]
    wrong = uv.copy()
    wrong[4] += [25.0, -18.0]  # an occluded wrist put elsewhere
    plain = pnp_base(ur5, Q, wrong, K, names=NAMES, base_pixel=base_uv)
    robust = pnp_base(ur5, Q, wrong, K, names=NAMES, base_pixel=base_uv, outlier_px=3.0)
    assert np.linalg.norm(plain[:3, 3] - pose[:3, 3]) > 0.01
    assert np.linalg.norm(robust[:3, 3] - pose[:3, 3]) < 1e-4
    # The base's pixel is used: moving it moves the answer.
    moved = pnp_base(ur5, Q, uv, K, names=NAMES, base_pixel=base_uv + [6.0, 0.0])
    assert np.linalg.norm(moved[:3, 3] - pose[:3, 3]) > 1e-3
    with pytest.raises(ValueError, match="base_pixel"):
        pnp_base(ur5, Q, uv, K, names=NAMES, base_pixel=[1.0, np.nan])
    with pytest.raises(ValueError, match="outlier_px"):
        pnp_base(ur5, Q, uv, K, names=NAMES, outlier_px=0.0)


def test_one_wrong_keypoint_does_not_drag_the_others_with_the_robust_cost(ur5):
    """A network misplaces whole keypoints: with Cauchy's cost (the default) the fit keeps
    the other keypoints near the truth; plain least squares spreads the error over all."""
    pose, points = scene(ur5, Q)
    uv = project(points)
    uv[4] += (25.0, -18.0)  # wrist_2 put 30 px away
    base = pose[:3, 3]
    errors = {}
    for robust in (3.0, None):
        fit = refine(ur5, points, names=NAMES, base=base, pixels=uv, intrinsics=K, robust=robust)
        others = np.delete(np.arange(len(NAMES)), 4)
        errors[robust] = np.linalg.norm(fit.keypoints[others] - points[others], axis=1).max()
    # measured: 1.0 cm robust, 17.9 cm least squares
    assert errors[3.0] < 0.02 and errors[None] > 5 * errors[3.0]
