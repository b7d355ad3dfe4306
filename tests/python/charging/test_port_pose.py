"""The port's pose: the plane fit (Eqs. 2-3) against numpy's least squares, the pose
from the pins exact on noise-free points for any turn about the axis, and the
refinement in both images against the truth."""

import numpy as np
import pytest

pytest.importorskip("cv2")

from earcore.charging.connectors import connector  # noqa: E402
from earcore.charging.port_pose import fit_plane, plane_normal, pose_from_points, refine_in_images  # noqa: E402
from earcore.charging.stereo import triangulate, verging_rig  # noqa: E402
from earcore.transforms import rotation_angle, rotation_from_vector  # noqa: E402

K = np.array([[2800.0, 0.0, 1023.5], [0.0, 2800.0, 767.5], [0.0, 0.0, 1.0]])


def random_port_pose(rng, distance=2.0):
    """A port facing the camera (its z towards the camera) tilted up to 45°, turned
    about its axis by anything."""
    facing = rotation_from_vector([np.pi, 0.0, 0.0])  # port z = −camera z
    tilt = rotation_from_vector(np.r_[rng.normal(size=2), 0.0] / np.sqrt(2) * np.radians(rng.uniform(0, 45)))
    turn = rotation_from_vector([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    pose = np.eye(4)
    pose[:3, :3] = tilt @ facing @ turn
    pose[:3, 3] = [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), distance]
    return pose


def errors(estimate, truth):
    return np.linalg.norm(estimate[:3, 3] - truth[:3, 3]), np.degrees(rotation_angle(estimate[:3, :3], truth[:3, :3]))


def test_plane_fit_solves_the_normal_equations():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.1, 0.1, (30, 2))
    z = 0.2 * xy[:, 0] - 0.1 * xy[:, 1] + 2.0
    assert fit_plane(np.c_[xy, z]) == pytest.approx((0.2, -0.1, 2.0), abs=1e-12)
    noisy = z + rng.normal(0, 0.003, len(z))
    reference = np.linalg.lstsq(np.c_[xy, np.ones(len(z))], noisy, rcond=None)[0]
    assert fit_plane(np.c_[xy, noisy]) == pytest.approx(tuple(reference), abs=1e-9)
    n = plane_normal(0.2, -0.1)
    assert n[2] < 0 and np.linalg.norm(n) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="collinear"):
        fit_plane(np.c_[np.linspace(0, 1, 5), np.linspace(0, 1, 5), np.ones(5)])


@pytest.mark.parametrize("name", ["type2", "type1"])
def test_pose_from_noise_free_pins_is_exact_for_any_turn(name):
    rng = np.random.default_rng(1)
    model = connector(name).reference_points
    for _ in range(20):
        truth = random_port_pose(rng)
        measured = model @ truth[:3, :3].T + truth[:3, 3]
        fit = pose_from_points(model, measured)
        t, r = errors(fit.camera_from_port, truth)
        assert t < 1e-9 and r < 1e-5  # degrees; arccos near 1 limits the precision
        assert fit.rms_m < 1e-9


def test_refinement_in_both_images_recovers_the_pose_and_beats_the_plane_with_noise():
    rng = np.random.default_rng(2)
    rig = verging_rig(K, 0.4, np.degrees(np.arctan(0.4 / 2.0)), size=(2048, 1536))
    model = connector("type2").reference_points
    plane_deg, refined_deg = [], []
    for _ in range(30):
        truth = random_port_pose(rng)
        left, right = rig.project(model @ truth[:3, :3].T + truth[:3, 3])
        start = truth.copy()
        start[:3, :3] = rotation_from_vector(rng.normal(size=3) * 0.03) @ truth[:3, :3]
        start[:3, 3] += rng.normal(size=3) * 0.003
        exact = refine_in_images(rig, start, model, left, right)
        t, r = errors(exact.camera_from_port, truth)
        assert t < 1e-6 and r < 1e-4 and exact.rms_px < 1e-4
        noisy_left, noisy_right = left + rng.normal(0, 0.2, left.shape), right + rng.normal(0, 0.2, right.shape)
        plane = pose_from_points(model, triangulate(rig, noisy_left, noisy_right))
        refined = refine_in_images(rig, plane, model, noisy_left, noisy_right)
        plane_deg.append(errors(plane.camera_from_port, truth)[1])
        refined_deg.append(errors(refined.camera_from_port, truth)[1])
    assert np.median(refined_deg) < np.median(plane_deg)


def test_pose_inputs_are_checked():
    model = connector("type2").reference_points
    with pytest.raises(ValueError, match="matching"):
        pose_from_points(model, model[:4])
    bent = model.copy()
    bent[0, 2] = 0.01
    with pytest.raises(ValueError, match="one plane"):
        pose_from_points(bent, model)
    # a layout on another plane of its frame (a plug's pins' tips, z = -20 mm) fits as well
    tips = model - [0.0, 0.0, 0.02]
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_vector([0.1, np.pi - 0.3, 0.05])  # z towards the camera
    pose[:3, 3] = [0.1, -0.05, 1.8]
    fit = pose_from_points(tips, tips @ pose[:3, :3].T + pose[:3, 3])
    assert np.abs(fit.camera_from_port - pose).max() < 1e-9
    rig = verging_rig(K, 0.4, 10.0)
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        refine_in_images(rig, np.eye(4), model, np.zeros((3, 2)), np.zeros((7, 2)))
