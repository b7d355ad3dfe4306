"""Calibration (Paper I): the board finder against rendered boards projected through
the true lens, corner depth against the true plane, the rigid and eye-to-hand fits and
both lens fits against synthetic data with known answers, the calibration file, bad
input, and the whole procedure in the cell against the simulation's ground truth
(including a bumped camera being noticed)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pose_reference import angle_deg, apply, make_pose, project  # noqa: E402

import earcore
from earcore.app.calibration_cell import calibration_cell, calibration_cell_config, evaluate
from earcore.calibration import (
    BoardNotSeen,
    Calibration,
    CalibrationConfig,
    CalibrationFileError,
    Calibrator,
    CameraCalibration,
    DegeneratePoses,
    PoorCalibration,
    TooFewFrames,
    calibrate_lens,
    calibrate_lens_on_robot,
    check_camera,
    corner_points,
    detect_board,
    fit_eye_to_hand,
    lens_displacement,
)
from earcore.calibration.board import Checkerboard, Detection
from earcore.calibration.eye_to_hand import fit_eye_to_hand_from_poses, refine_by_reprojection
from earcore.calibration.procedure import refuse_uncertain
from earcore.depth_error import DepthBias, radius2_grid
from earcore.transforms import look_at, mean_pose, perturb_pose

BOARD = Checkerboard()












# --- rigid fits -------------------------------------------------------------------


def test_rigid_fit_matches_the_svd_reference_and_ransac_drops_outliers():
    rng = np.random.default_rng(0)
    truth = make_pose(rng.normal(size=3), rng.normal(size=3))
    src = rng.uniform(-0.5, 0.5, (50, 3))
    dst = apply(truth, src) + rng.normal(scale=1e-3, size=(50, 3))
    # Reference: Kabsch written out with numpy's SVD.
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.diag([1, 1, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    fit = earcore.rigid_fit(src, dst)
    assert np.allclose(fit[:3, :3], r, atol=1e-10)
    assert np.allclose(fit[:3, 3], cd - r @ cs, atol=1e-10)
    dst[::5] += [0.0, 0.0, 0.2]  # 10 gross outliers
    m, inliers, rmse = earcore.rigid_fit_ransac(src, dst, 0.01, 200, 3)
    assert inliers.sum() == 40 and not inliers[::5].any()
    assert np.abs(m - truth).max() < 2e-3 and rmse < 3e-3


@pytest.mark.parametrize(
    "src, dst, error",
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
        (np.eye(3), np.eye(4)[:, :3], "pair up"),
        (np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), np.zeros((3, 3)), "collinear"),
        (np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0.0]]), np.eye(3), "not finite"),
    ],
)
def test_rigid_fit_rejects_bad_input(src, dst, error):
    with pytest.raises(ValueError, match=error):
        earcore.rigid_fit(src, dst)


# --- eye-to-hand ------------------------------------------------------------------


def _synthetic_frames(rng, x, z, count=30, tilt=0.4, noise=0.001):
    flanges = [make_pose(rng.normal(size=3) * tilt, [0.45, 0.2, 0.4] + rng.normal(size=3) * 0.1) for _ in range(count)]
    corners = BOARD.inner_corners()
    cams = [apply(np.linalg.inv(x) @ f @ z, corners) + rng.normal(scale=noise, size=corners.shape) for f in flanges]
    return cams, np.array(flanges), corners


def test_eye_to_hand_recovers_camera_and_mount():
    rng = np.random.default_rng(1)
    x = look_at([1.2, 1.0, 0.9], [0.3, 0.0, 0.2])
    z = make_pose([0.02, -0.015, 0.01], [0.004, -0.003, 0.103])
    cams, flanges, corners = _synthetic_frames(rng, x, z)
    cams[3][5] += 0.05  # a corner with a wrong depth
    cams[7][:] = np.nan  # a frame without depth
    designed = make_pose([0, 0, 0], [0, 0, 0.1])
    fit = fit_eye_to_hand(cams, flanges, corners, designed)
    assert np.abs(fit.base_from_camera[:3, 3] - x[:3, 3]).max() < 1e-3
    assert np.abs(fit.flange_from_board[:3, 3] - z[:3, 3]).max() < 1e-3
    assert angle_deg(fit.flange_from_board, z) < 0.2 and angle_deg(fit.base_from_camera, x) < 0.2
    assert fit.frames == 29 and fit.corners == 29 * 24 - 1
    # With the designed mount taken as true, the mount's error lands in the camera pose.
    fixed = fit_eye_to_hand(cams, flanges, corners, designed, estimate_mount=False)
    assert np.linalg.norm(fixed.base_from_camera[:3, 3] - x[:3, 3]) > 2e-3


def test_eye_to_hand_reports_degenerate_and_too_few_frames():
    rng = np.random.default_rng(2)
    x = look_at([1.2, 1.0, 0.9], [0.3, 0.0, 0.2])
    z = make_pose([0, 0, 0], [0, 0, 0.1])
    cams, flanges, corners = _synthetic_frames(rng, x, z, count=10, tilt=0.0)
    flanges[:, :3, :3] = np.eye(3)  # translation only: the mount cannot be told apart
    cams = [apply(np.linalg.inv(x) @ f @ z, corners) for f in flanges]
    with pytest.raises(DegeneratePoses, match="cam_a.*turned"):
        fit_eye_to_hand(cams, flanges, corners, z, camera="cam_a")
    with pytest.raises(TooFewFrames, match="cam_b.*0 usable frames"):
        fit_eye_to_hand([], np.zeros((0, 4, 4)), corners, z, camera="cam_b")


def _small_turn(rng, degrees):
    axis = rng.normal(size=3)
    return make_pose(axis / np.linalg.norm(axis) * math.radians(degrees), rng.normal(size=3) * 1e-3)


def test_ax_zb_recovers_camera_and_mount_from_board_poses():
    """A colour-only camera: each frame's board pose (as PnP would give it, with a
    little noise) and the flange's; OpenCV's AX = ZB finds the camera and the mount."""
    rng = np.random.default_rng(3)
    x = look_at([1.2, 1.0, 0.9], [0.3, 0.0, 0.2])
    z = make_pose([0.02, -0.015, 0.01], [0.004, -0.003, 0.103])
    _, flanges, corners = _synthetic_frames(rng, x, z, count=25)
    poses = np.array([np.linalg.inv(x) @ f @ z @ _small_turn(rng, 0.05) for f in flanges])
    fit = fit_eye_to_hand_from_poses(poses, flanges, corners, camera="webcam")
    assert np.linalg.norm(fit.base_from_camera[:3, 3] - x[:3, 3]) < 2e-3 and angle_deg(fit.base_from_camera, x) < 0.1
    assert np.linalg.norm(fit.flange_from_board[:3, 3] - z[:3, 3]) < 2e-3 and angle_deg(fit.flange_from_board, z) < 0.1
    assert fit.frames == 25 and fit.rmse < 3e-3
    exact = np.array([np.linalg.inv(x) @ f @ z for f in flanges])
    li = fit_eye_to_hand_from_poses(exact, flanges, corners, method="li")
    assert np.abs(li.base_from_camera - x).max() < 1e-6 and li.rmse < 1e-6
    # Tsai-Lenz (from relative motions, the mount after): exact on exact poses, close on noisy ones
    tsai = fit_eye_to_hand_from_poses(exact, flanges, corners, method="tsai")
    assert np.abs(tsai.base_from_camera - x).max() < 1e-6 and np.abs(tsai.flange_from_board - z).max() < 1e-6
    tsai = fit_eye_to_hand_from_poses(poses, flanges, corners, method="tsai")
    assert np.linalg.norm(tsai.base_from_camera[:3, 3] - x[:3, 3]) < 3e-3 and angle_deg(tsai.base_from_camera, x) < 0.15
    # Bad input: too few frames, no rotation variety, wrong counts, unknown method.
    with pytest.raises(TooFewFrames, match="webcam"):
        fit_eye_to_hand_from_poses(exact[:2], flanges[:2], corners, camera="webcam")
    still = flanges.copy()
    still[:, :3, :3] = np.eye(3)
    with pytest.raises(DegeneratePoses, match="webcam.*turned"):
        fit_eye_to_hand_from_poses(exact, still, corners, camera="webcam")
    with pytest.raises(ValueError, match="board poses"):
        fit_eye_to_hand_from_poses(exact[:5], flanges, corners)
    with pytest.raises(ValueError, match="method"):
        fit_eye_to_hand_from_poses(exact, flanges, corners, method="lenz")


def test_reprojection_refinement_recovers_camera_and_mount():
    """Pixels only (a colour-only camera): from a camera pose 2 cm / 1° and a mount 3 mm /
    1° off, the joint reprojection fit lands on the truth."""
    rng = np.random.default_rng(6)
    x = look_at([0.9, 0.6, 0.8], [0.45, 0.0, 0.3])
    z = make_pose([0.02, -0.015, 0.01], [0.004, -0.003, 0.103])
    _, flanges, corners = _synthetic_frames(rng, x, z, count=30, tilt=0.3)
    pixels, keep = [], []
    for i, f in enumerate(flanges):
        cam = apply(np.linalg.inv(x) @ f @ z, corners)
        if (cam[:, 2] > 0.2).all():
            pixels.append(project(cam, K_TRUE, D_TRUE) + rng.normal(scale=0.1, size=(len(corners), 2)))
            keep.append(i)
    x0 = x @ make_pose([0.0, 0.0, math.radians(1.0)], [0.02, 0.0, 0.0])
    z0 = z @ make_pose([math.radians(1.0), 0.0, 0.0], [0.0, 0.003, 0.0])
    fx, fz, rms = refine_by_reprojection(pixels, flanges[keep], corners, K_TRUE, D_TRUE, x0, z0)
    assert np.linalg.norm(fx[:3, 3] - x[:3, 3]) < 1e-3 and angle_deg(fx, x) < 0.05
    assert np.linalg.norm(fz[:3, 3] - z[:3, 3]) < 1e-3 and angle_deg(fz, z) < 0.1
    assert rms == pytest.approx(0.1 * math.sqrt(2), rel=0.15)  # what is left is the pixel noise (2D rms)


def test_mean_pose_is_the_centre_of_nearby_poses():
    rng = np.random.default_rng(4)
    centre = make_pose([0.3, -0.2, 0.1], [0.5, 0.1, 0.2])
    poses = np.array([centre @ _small_turn(rng, 2.0) for _ in range(400)])
    mean = mean_pose(poses)
    assert angle_deg(mean, centre) < 0.2 and np.abs(mean[:3, 3] - centre[:3, 3]).max() < 3e-4
    assert np.allclose(mean[:3, :3] @ mean[:3, :3].T, np.eye(3))


# --- lenses ------------------------------------------------------------------------

K_TRUE = np.array([[361.6, 0.0, 255.5], [0.0, 367.2, 211.5], [0.0, 0.0, 1.0]])
D_TRUE = np.array([0.09, -0.27, 0.0, 0.0, 0.09])


def _views(rng, count, distance=(0.45, 0.8)):
    """Board poses in front of the camera, tilted up to ~35°, over the image."""
    views = []
    while len(views) < count:
        d = rng.uniform(*distance)
        centre = np.array([rng.uniform(-0.45, 0.45) * d, rng.uniform(-0.35, 0.35) * d, d])
        pose = make_pose([math.pi + rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)], centre)
        px = project(apply(pose, BOARD.inner_corners()), K_TRUE, D_TRUE)
        if (px > 2).all() and (px[:, 0] < 509).all() and (px[:, 1] < 421).all():
            views.append((pose, px))
    return views


def test_zhang_recovers_the_lens_from_clean_views():
    rng = np.random.default_rng(3)
    views = _views(rng, 40)
    detections = [Detection(px + rng.normal(scale=0.05, size=px.shape), (512, 424)) for _, px in views]
    fit = calibrate_lens(detections, BOARD.inner_corners(), np.array([[340.0, 0, 250], [0, 340.0, 205], [0, 0, 1]]))
    assert fit.rms < 0.1
    seen = np.concatenate([d.corners for d in detections])
    region = (*np.ceil(seen.min(0)).astype(int), *np.floor(seen.max(0)).astype(int))
    # Zhang's method trades focal length against each board's distance a little: ~0.2 %.
    assert np.abs(fit.K - K_TRUE).max() < 1.0
    assert lens_displacement(fit.K, fit.distortion, K_TRUE, D_TRUE, (512, 424), region=region) < 1.5


def test_lens_on_robot_recovers_lens_and_pose():
    """All frames' corners in the base frame: one 3D rig seen from one pose."""
    rng = np.random.default_rng(4)
    base_from_camera = look_at([1.1, 0.8, 0.8], [0.4, 0.0, 0.3])
    views = _views(rng, 30, distance=(0.7, 1.0))
    points = np.concatenate([apply(base_from_camera @ pose, BOARD.inner_corners()) for pose, _ in views])
    pixels = np.concatenate([px for _, px in views]) + rng.normal(scale=0.1, size=(len(points), 2))
    lens, pose = calibrate_lens_on_robot(points, pixels, (512, 424), np.array([[350.0, 0, 250], [0, 350.0, 210], [0, 0, 1]]))
    assert abs(lens.K[0, 0] - K_TRUE[0, 0]) < 1.0 and abs(lens.K[1, 2] - K_TRUE[1, 2]) < 1.0
    assert np.linalg.norm(pose[:3, 3] - base_from_camera[:3, 3]) < 2e-3
    assert lens.rms == pytest.approx(0.1 * math.sqrt(2), rel=0.15)  # 0.1 px per axis


def test_a_lens_guess_outside_the_image_is_refused_with_the_camera_named():
    """OpenCV rejects a principal point outside the image; the caller gets a calibration
    error naming the camera (a re-fit from a poor frame subset can guess that badly)."""
    rng = np.random.default_rng(4)
    base_from_camera = look_at([1.1, 0.8, 0.8], [0.4, 0.0, 0.3])
    views = _views(rng, 10, distance=(0.7, 1.0))
    points = np.concatenate([apply(base_from_camera @ pose, BOARD.inner_corners()) for pose, _ in views])
    pixels = np.concatenate([px for _, px in views])
    off = np.array([[350.0, 0, 900], [0, 350.0, 210], [0, 0, 1]])
    with pytest.raises(DegeneratePoses, match="'left'.*lens fit on the robot failed: Principal point must be within the image"):
        calibrate_lens_on_robot(points, pixels, (512, 424), off, camera="left")
    with pytest.raises(DegeneratePoses, match="'left'.*Zhang's method failed"):
        calibrate_lens([Detection(px, (512, 424)) for _, px in views], BOARD.inner_corners(), off, camera="left")


def test_zhang_needs_frames_and_coverage():
    rng = np.random.default_rng(5)
    views = _views(rng, 10)
    with pytest.raises(TooFewFrames, match="cam_c"):
        calibrate_lens([Detection(px, (512, 424)) for _, px in views[:3]], BOARD.inner_corners(), K_TRUE, camera="cam_c")
    same = [Detection(views[0][1], (512, 424))] * 10  # the board in one spot only
    with pytest.raises(DegeneratePoses, match="covered only"):
        calibrate_lens(same, BOARD.inner_corners(), K_TRUE)


# --- the board in rendered images --------------------------------------------------


@pytest.fixture(scope="module")
def board_scene():
    pybullet = pytest.importorskip("pybullet")
    from pybullet_utils.bullet_client import BulletClient

    from earcore.sim.camera import SimulatedCamera
    from earcore.sim.sensors import SENSORS
    from earcore.sim.tools import visual_shape
    from earcore.transforms import quaternion

    client = BulletClient(pybullet.DIRECT)
    shape, texture = visual_shape(BOARD, client)
    body = client.createMultiBody(0, -1, shape, [0, 0, 0])
    client.changeVisualShape(body, -1, textureUniqueId=texture)
    sensor = SENSORS["kinect_v2"]
    camera_pose = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], up=(0, -1, 0))
    camera = SimulatedCamera(client, "cam", sensor, camera_pose, rng=np.random.default_rng(0), supersample=2)

    def place(base_from_board):
        x, y, z, w = quaternion(base_from_board[:3, :3])
        client.resetBasePositionAndOrientation(body, base_from_board[:3, 3].tolist(), [x, y, z, w])

    yield camera, place
    client.disconnect()


@pytest.mark.parametrize("roll_deg", [0, 90, 180, 270])
def test_board_corners_and_orientation_against_the_true_lens(board_scene, roll_deg):
    """Each corner lands within 0.35 px of the true corner projected through the true
    lens, in the board's own order whichever way the board is turned."""
    camera, place = board_scene
    pose = make_pose([math.pi, 0.0, 0.0], [0.12, -0.05, 0.75]) @ make_pose([0.3, -0.25, math.radians(roll_deg)], [0, 0, 0])
    place(pose)
    image, depth, _ = camera.render_true()
    detection = detect_board(image, BOARD)
    assert detection is not None
    truth = project(apply(pose, BOARD.inner_corners()), camera.sensor.intrinsics, camera.sensor.distortion)
    assert np.abs(detection.corners - truth).max() < 0.35
    # Corner depth: both methods against the true corners (1 m, Kinect V2 noise ~1.5 mm),
    # the sensor's depth error taken out as a calibrated camera would.
    sensor = camera.sensor
    frames = np.stack([sensor.corrupt(depth, np.random.default_rng(i)) for i in range(5)])
    frames = sensor.depth_bias.correct(frames, radius2_grid(sensor.intrinsics, sensor.width, sensor.height))
    for method, bound in (("median", 0.004), ("plane", 0.002)):
        points = corner_points(detection, frames, camera.sensor.intrinsics, camera.sensor.distortion, method=method)
        assert np.linalg.norm(points - apply(pose, BOARD.inner_corners()), axis=1).max() < bound, method


def test_board_out_of_view_or_cut_is_not_detected(board_scene):
    camera, place = board_scene
    place(make_pose([math.pi, 0.0, 0.0], [0.0, 0.0, -1.0]))  # behind the camera
    assert detect_board(camera.render_true()[0], BOARD) is None
    place(make_pose([math.pi, 0.0, 0.0], [0.72, 0.0, 1.0]))  # half out of the image
    assert detect_board(camera.render_true()[0], BOARD) is None


# --- the calibration file -----------------------------------------------------------


# --- depth error (Paper I's depth distortion) ------------------------------------------


def test_depth_error_fit_recovers_the_model_and_correct_inverts_it():
    rng = np.random.default_rng(5)
    truth = DepthBias(offset=0.003, scale=-0.004, radial=0.007)
    z = rng.uniform(0.7, 1.6, 3000)
    rho2 = rng.uniform(0.0, 0.8, 3000)
    measured = z + truth.error(z, rho2) + rng.normal(0, 0.0005, 3000)
    measured[:30] += 0.05  # corners whose depth hit the board's edge
    fit = DepthBias.fit(measured, z, rho2)
    assert fit.offset == pytest.approx(truth.offset, abs=3e-4)
    assert fit.scale == pytest.approx(truth.scale, abs=3e-4)
    assert fit.radial == pytest.approx(truth.radial, abs=2e-4)
    exact = z + truth.error(z, rho2)
    assert np.abs(truth.correct(exact, rho2) - z).max() < 1e-7  # first-order inversion is exact enough
    assert truth.correct(np.zeros(3), 0.5).tolist() == [0.0, 0.0, 0.0]  # no return stays no return
    with pytest.raises(ValueError, match="at least 10"):
        DepthBias.fit(z[:5], z[:5], rho2[:5])


def test_radius2_grid_is_the_normalised_image_radius():
    grid = radius2_grid(K_TRUE, 512, 424)
    u, v = 100, 300
    assert grid[v, u] == pytest.approx(((u - K_TRUE[0, 2]) / K_TRUE[0, 0]) ** 2 + ((v - K_TRUE[1, 2]) / K_TRUE[1, 1]) ** 2)
    crop = radius2_grid(K_TRUE, 50, 40, origin=(u, v))
    assert crop[0, 0] == pytest.approx(grid[v, u]) and crop[39, 49] == pytest.approx(grid[v + 39, u + 49])


def _entry(name="cam"):
    return CameraCalibration(
        name=name, base_from_camera=look_at([1, 1, 1], [0, 0, 0]), depth_K=K_TRUE, depth_distortion=D_TRUE,
        depth_size=(512, 424), frames=30, corners=700, start_q=[0.1, -1.0, 1.0, 0.0, 1.5, 0.0],
        depth_error=[0.002, 0.001, -0.005],
    )


def test_calibration_file_round_trip_and_merge(tmp_path):
    path = tmp_path / "cal.yaml"
    Calibration({"a": _entry("a"), "b": _entry("b")}).save(path)
    loaded = Calibration.load(path)
    assert set(loaded.cameras) == {"a", "b"}
    a = loaded.cameras["a"]
    assert np.allclose(a.base_from_camera, _entry().base_from_camera) and a.depth_size == (512, 424)
    assert a.colour_K is None and math.isnan(a.eye_to_hand_rmse) and a.start_q == pytest.approx(_entry().start_q)
    assert a.depth_error == pytest.approx([0.002, 0.001, -0.005]) and a.depth_bias == DepthBias(0.002, 0.001, -0.005)
    moved = _entry("b")
    moved.base_from_camera = np.eye(4)
    merged = loaded.merged({"b": moved})
    assert np.allclose(merged.cameras["b"].base_from_camera, np.eye(4))
    assert np.allclose(merged.cameras["a"].base_from_camera, a.base_from_camera)


_GOOD = ("version: 1\ncameras:\n- {name: a, base_from_camera: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "
         "depth_K: [[1,0,0],[0,1,0],[0,0,1]], depth_distortion: [0,0,0,0,0], depth_size: [1, 1]}\n")


@pytest.mark.parametrize(
    "text, error",
    [
        ("{not yaml: [", "not valid YAML"),
        ("version: 1\ncameras: 3\n", "not an earcore calibration"),
        ("version: 1\ncameras:\n- name: a\n", "missing 'base_from_camera'"),
        ("version: 1\ncameras:\n- {name: a, base_from_camera: [[1, 0], [0, 1]], depth_K: [], depth_distortion: [], depth_size: [1, 1]}\n", "shape"),
        ("version: 1\ncameras:\n- {name: a, base_from_camera: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], depth_K: [[1,0,0],[0,1,0],[0,0,1]], "
         "depth_distortion: [0,0,0,0,0], depth_size: [1, 1], depth_error: [0.1, .nan]}\n", "depth_error"),
        # Values that parse but cannot be a lens or a pose, each naming the file, camera and key.
        (_GOOD.replace("depth_K: [[1,0,0]", "depth_K: [[0,0,0]"), r"cameras\[0\] \('a'\): depth_K is not a camera matrix"),
        (_GOOD.replace("base_from_camera: [[1,0,0,0]", "base_from_camera: [[2,0,0,0]"), r"\('a'\): base_from_camera is not a rigid"),
        (_GOOD.replace("base_from_camera: [[1,0,0,0]", "base_from_camera: [[abc,0,0,0]"), r"\('a'\): base_from_camera must be numbers"),
        (_GOOD.replace("depth_size: [1, 1]", "depth_size: [x, 1]"), "depth_size must be whole numbers"),
    ],
)
def test_corrupt_calibration_files_are_clear_errors(tmp_path, text, error):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationFileError, match=error):
        Calibration.load(path)
    with pytest.raises(CalibrationFileError, match="no such"):
        Calibration.load(tmp_path / "missing.yaml")


def test_perception_uses_the_calibrated_lens_and_pose():
    from earcore.interfaces import Frame
    from earcore.perception.config import PerceptionConfig
    from earcore.perception.pipeline import PerceptionPipeline

    pipeline = PerceptionPipeline(PerceptionConfig(), earcore.robots.load("ur5"))
    entry = _entry("cam")
    pipeline.load_calibration(Calibration({"cam": entry}))
    # A plane at 1.5 m as the camera would read it with the calibrated depth error.
    rho2 = radius2_grid(K_TRUE, 512, 424)
    depth = 1.5 + entry.depth_bias.error(1.5, rho2)
    frame = Frame("cam", 0.0, np.zeros((424, 512, 3), np.uint8), depth, np.eye(3), np.eye(4))
    points = pipeline.frame_points(frame, base_from_camera=pipeline.camera_pose(frame))
    expected = earcore.depth_to_points(
        np.full((424, 512), 1.5), *K_TRUE[[0, 1, 0, 1], [0, 1, 2, 2]], distortion=D_TRUE, base_from_camera=entry.base_from_camera
    )
    assert np.abs(points - expected).max() < 1e-6
    # Images of another size (another camera scale) would be read through a lens fitted
    # at 512×424: refused, naming the camera and both sizes, not mapped off by pixels.
    half = Frame("cam", 0.0, np.zeros((212, 256, 3), np.uint8), depth[::2, ::2], np.eye(3), np.eye(4))
    with pytest.raises(CalibrationFileError, match=r"'cam' was calibrated on depth images of 512×424 .* 256×212"):
        pipeline.frame_points(half)


# --- Algorithm 1 in the cell ---------------------------------------------------------


@pytest.fixture(scope="module")
def calibrated_v1():
    """The Kinect V1-like camera (320×240: quick renders) calibrated with a short
    trajectory: at most 20 frames (`earcore calibrate`'s default)."""
    config = calibration_cell_config(seed=3)
    config.cameras = [c for c in config.cameras if c.name == "kinect_v1_front"]
    cell, mount = calibration_cell(config, seed=3)
    settings = CalibrationConfig(max_frames=20, seed=3)
    calibrator = Calibrator(cell, settings)
    result = calibrator.run()["kinect_v1_front"]
    yield cell, mount, calibrator, result
    cell.close()


@pytest.mark.slow
def test_algorithm_1_finds_the_camera_the_lens_and_the_mount(calibrated_v1):
    cell, mount, calibrator, result = calibrated_v1
    errors = evaluate(cell, result, mount, calibrator.observations[result.name])
    assert result.frames <= 20
    assert errors.translation < 0.005 and errors.rotation_deg < 0.5, errors  # ≤ 30 frames
    assert errors.mount_translation < 0.003
    assert result.depth_reprojection_rms < 0.5
    assert errors.depth_lens_px < 1.5 and errors.colour_lens_px < 2.0, errors
    assert errors.offset_translation < 0.004 and errors.offset_rotation_deg < 0.3, errors
    # The sensor's depth error (+0.3 % of z, −6 mm radial): the terms the data fix are
    # found; the offset takes the pose's error along the view (pixels fix the distance
    # only through perspective: the weak direction, Paper I's larger Z error).
    fitted, true = result.depth_bias, cell.cameras[0].sensor.depth_bias
    assert fitted.scale == pytest.approx(true.scale, abs=8e-4), fitted
    assert fitted.radial == pytest.approx(true.radial, abs=3.5e-3), fitted  # V1: the board rarely reaches the corners
    assert fitted.offset == pytest.approx(errors.translation_xyz[2], abs=1.5e-3), (fitted, errors)
    assert abs(errors.translation_xyz[2]) >= max(abs(errors.translation_xyz[0]), abs(errors.translation_xyz[1])), errors
    assert calibrator.motion_time < 65.0  # its share of three cameras in 3 minutes (README: 165 s for the three)


@pytest.mark.slow
def test_the_reported_uncertainty_covers_the_error_and_gates_the_result(calibrated_v1):
    cell, mount, calibrator, result = calibrated_v1
    errors = evaluate(cell, result, mount, calibrator.observations[result.name])
    assert result.pose_sigma_m == pytest.approx(math.hypot(result.pixel_pose_sigma_m, result.pose_agreement_m))
    assert result.pose_sigma_deg == pytest.approx(math.hypot(result.pixel_pose_sigma_deg, result.pose_agreement_deg))
    assert errors.translation <= 3 * result.pose_sigma_m, (errors.translation, result.pose_sigma_m)
    assert errors.rotation_deg <= 3 * result.pose_sigma_deg, (errors.rotation_deg, result.pose_sigma_deg)
    config = calibrator.config
    refuse_uncertain(result, config)  # it passed the default limits
    with pytest.raises(PoorCalibration, match=r"'kinect_v1_front': pose uncertain to ±.* beyond [0-9.]+ mm / 0.5°: the pose from pixels alone"):
        refuse_uncertain(result, replace(config, max_pose_sigma_m=0.9 * result.pose_sigma_m))
    with pytest.raises(PoorCalibration, match=r"beyond [0-9.]+°: .*from pixels and from depth"):
        refuse_uncertain(result, replace(config, max_pose_sigma_m=None, max_pose_sigma_deg=0.9 * result.pose_sigma_deg))
    refuse_uncertain(result, replace(config, max_pose_sigma_m=None, max_pose_sigma_deg=None))
    unsure = replace(result, pose_sigma_m=math.nan)  # an uncertainty that could not be computed is no pass
    with pytest.raises(PoorCalibration):
        refuse_uncertain(unsure, config)


@pytest.mark.slow
def test_a_bumped_camera_is_noticed(calibrated_v1):
    cell, mount, calibrator, result = calibrated_v1
    ok = check_camera(calibrator, result)
    assert ok.seen and not ok.moved and ok.residual < 0.005, ok
    cam = cell.cameras[0]
    original = cam.base_from_camera
    try:
        cam.place(perturb_pose(original, 0.10, math.radians(10.0), np.random.default_rng(0)))
        bumped = check_camera(calibrator, result)
        assert bumped.moved and "MOVED" in str(bumped)
    finally:
        cam.place(original)
    # A calibration made on images of another size is not compared at all.
    w, h = result.depth_size
    with pytest.raises(CalibrationFileError, match=f"{2 * w}×{2 * h} pixels, but its images are {w}×{h}"):
        check_camera(calibrator, replace(result, depth_size=(2 * w, 2 * h)))


@pytest.mark.slow
def test_a_colour_only_camera_is_calibrated_from_its_images(tmp_path):
    """A camera without depth (the webcam preset, at half resolution for speed) where
    the Kinect V1 stands: AX = ZB from the board's poses, then lens, pose and mount from
    the pixels; the file keeps it without depth entries and the perception loop skips it."""
    from earcore.perception.config import PerceptionConfig
    from earcore.perception.pipeline import PerceptionPipeline
    from earcore.sim.config import CameraConfig

    config = calibration_cell_config(seed=1, camera_scale=0.5)
    v1 = next(c for c in config.cameras if c.name == "kinect_v1_front")
    config.cameras = [CameraConfig("webcam_front", "webcam", v1.position, v1.target)]
    cell, mount = calibration_cell(config, seed=1)
    try:
        calibrator = Calibrator(cell, CalibrationConfig(max_frames=20, seed=1))
        result = calibrator.run_to_file(tmp_path / "cal.yaml")["webcam_front"]
        errors = evaluate(cell, result, mount, calibrator.observations["webcam_front"])
        assert not result.has_depth and result.colour_K is not None and result.depth_error is None
        assert errors.translation < 0.005 and errors.rotation_deg < 0.5, errors
        assert errors.mount_translation < 0.001 and errors.colour_lens_px < 1.5, errors
        assert result.colour_reprojection_rms < 0.5
        # Its uncertainty is the pixel fit's (pose and mount from the same pixels).
        assert result.pose_sigma_m == result.pixel_pose_sigma_m and result.pose_sigma_deg == result.pixel_pose_sigma_deg
        assert errors.translation <= 3 * result.pose_sigma_m and errors.rotation_deg <= 3 * result.pose_sigma_deg, (errors, result.pose_sigma_m)
        loaded = Calibration.load(tmp_path / "cal.yaml").cameras["webcam_front"]
        assert loaded.pose_sigma_m == pytest.approx(result.pose_sigma_m)
        assert loaded.depth_K is None and np.allclose(loaded.base_from_camera, result.base_from_camera)
        pipeline = PerceptionPipeline(PerceptionConfig(), earcore.robots.load("ur5"))
        pipeline.load_calibration(Calibration({"webcam_front": loaded}))
        assert "webcam_front" not in pipeline.poses
        assert check_camera(calibrator, result).residual < 0.005
        cam = cell.cameras[0]
        cam.place(perturb_pose(cam.base_from_camera, 0.10, math.radians(10.0), np.random.default_rng(0)))
        assert check_camera(calibrator, result).moved
    finally:
        cell.close()


def test_a_camera_that_never_sees_the_board_names_itself_and_writes_nothing(tmp_path):
    from earcore.sim.config import CameraConfig

    config = calibration_cell_config(seed=0, camera_scale=0.5)
    config.cameras = [CameraConfig("looks_at_the_floor", "kinect_v1", (2.5, 2.5, 1.0), (3.5, 3.5, -0.75))]
    cell, _ = calibration_cell(config, pose_error=(0.0, 0.0))
    path = tmp_path / "cal.yaml"
    Calibration({"kept": _entry("kept")}).save(path)
    before = path.read_bytes()
    calibrator = Calibrator(cell, CalibrationConfig(sweep_elevations_deg=(15.0,)))
    with pytest.raises(BoardNotSeen, match=r"looks_at_the_floor.*in images of 160×120 pixels"):
        calibrator.run_to_file(path)
    assert path.read_bytes() == before
    cell.close()


def test_a_file_that_is_not_a_readable_calibration_is_refused_before_the_robot_moves(tmp_path):
    """Recalibrating into a file merges into it; one this cannot read (a config file, an
    entry lacking a lens) was overwritten, losing the other cameras' entries. It is
    refused before any frame is taken, and left as it was."""
    config = calibration_cell_config(seed=0, camera_scale=0.5)
    cell, _ = calibration_cell(config, pose_error=(0.0, 0.0))
    calibrator = Calibrator(cell, CalibrationConfig())
    other = tmp_path / "cell.toml"
    other.write_text("[cell]\nseed = 3\n")
    broken = tmp_path / "two.yaml"
    Calibration({"kept": _entry("kept")}).save(broken)
    broken.write_text(broken.read_text() + "  lacking:\n    base_from_camera: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    for path in (other, broken):
        before = path.read_bytes()
        with pytest.raises(CalibrationFileError, match="not overwriting it"):
            calibrator.run_to_file(path)
        assert path.read_bytes() == before
    with pytest.raises(CalibrationFileError, match="is a folder"):
        calibrator.run_to_file(tmp_path)
    assert calibrator.observations == {} or not any(calibrator.observations.values())
    cell.close()


def test_calibrate_command_rejects_unknown_cameras_and_missing_files(tmp_path, capsys):
    from earcore.app.cli import main

    assert main(["calibrate", "--camera", "no_such_camera", "--out", str(tmp_path / "c.yaml")]) == 2
    assert "no_such_camera" in capsys.readouterr().err
    assert main(["calibrate", "--check", "--out", str(tmp_path / "missing.yaml")]) == 2
    assert "no such calibration file" in capsys.readouterr().err


def test_table_rows_select_the_frames_they_describe():
    from earcore.app.experiments.calibration import ROWS, Row, select
    from earcore.calibration.estimate import Observation

    def frame(phase, tilted=False, factor=None, radius=None, slot=None):
        return Observation("c", np.zeros(6), np.eye(4), Detection(np.zeros((24, 2)), (8, 8)), None, np.zeros((1, 1, 1)),
                           (0, 0), tilted, phase, factor, radius, slot)

    frames = [frame("start")] + [frame("tilt", True) for _ in range(6)]
    frames += [frame("stage", j % 2 == 1, f, r, j) for r, n in ((0.0, 1), (0.3, 6), (0.8, 12)) for j in range(n) for f in (1.0, 1.2)]
    assert len(select(frames, ROWS[0])) == len(frames) == 45
    no_overlap = select(frames, Row("x", overlap=False))
    assert all(o.slot is None or o.slot % 2 == 0 for o in no_overlap) and len(no_overlap) == 7 + 2 * (1 + 3 + 6)
    # Counted by hand: 7 start and tilt frames always; stage slots j at two factors each,
    # odd j tilted (radius 0: j = 0; 0.3 m: 3 of 6; 0.8 m: 6 of 12).
    untilted = select(frames, Row("x", tilting=False))
    assert len(untilted) == 7 + 2 * (1 + 3 + 6)
    assert not any(o.tilted for o in untilted if o.phase == "stage")
    centre = select(frames, Row("x", field="centre"))
    assert len(centre) == 7 + 2 * (1 + 6)
    assert all(o.radius is None or o.radius <= 0.5 for o in centre)
    assert len(select(frames, Row("x", tilting=False, field="centre"))) == 7 + 2 * (1 + 3)
    twenty = select(frames, Row("x", frames=20))
    assert len(twenty) == 20 and sum(o.phase != "stage" for o in twenty) == 7
    radii = {o.radius for o in twenty if o.phase == "stage"}
    assert radii == {0.0, 0.3, 0.8}  # spread over the trajectory, not its first frames
