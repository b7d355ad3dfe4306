"""Calibration's estimation without a robot or a simulator: observations synthesised
from a known camera pose, lens and board mount (pixels by OpenCV's projection, depth
by intersecting each pixel's ray with the board's plane) go through `Estimator.finish`,
which must give back the pose, the lens and the mount."""

from __future__ import annotations

import math

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from pose_reference import angle_deg, apply, make_pose  # noqa: E402

from earcore.calibration import CalibrationConfig, Checkerboard, Estimator, Observation, SensorSpec, TooFewFrames  # noqa: E402
from earcore.calibration.board import Detection  # noqa: E402

BOARD = Checkerboard()
SIZE = (512, 424)
K_TRUE = np.array([[361.6, 0.0, 255.5], [0.0, 367.2, 211.5], [0.0, 0.0, 1.0]])
D_TRUE = np.array([0.09, -0.27, 0.0, 0.0, 0.09])
#: The datasheet's pinhole: what the estimator starts from.
K_DATASHEET = np.array([[365.0, 0.0, 256.0], [0.0, 365.0, 212.0], [0.0, 0.0, 1.0]])








BASE_FROM_CAMERA = make_pose([2.1, -0.9, 0.4], [1.2, 0.7, 0.9])
MOUNT = make_pose([0.03, -0.02, 0.01], [0.004, -0.003, 0.103])


def _depth_region(cam_from_board: np.ndarray, corners_px: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """The depth image around the board (the crop Calibrator keeps): each pixel's ray,
    undistorted through the true lens, meets the board's plane; 0 off the board."""
    lo = np.maximum(np.floor(corners_px.min(axis=0)).astype(int) - 40, 0)
    hi = np.minimum(np.ceil(corners_px.max(axis=0)).astype(int) + 40, SIZE)
    u, v = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    rays = cv2.undistortPoints(pixels[:, None], K_TRUE, D_TRUE).reshape(-1, 2)
    rays = np.c_[rays, np.ones(len(rays))]
    normal, origin = cam_from_board[:3, 2], cam_from_board[:3, 3]
    z = (normal @ origin) / (rays @ normal)
    on_board = apply(np.linalg.inv(cam_from_board), rays * z[:, None])
    w, h = BOARD.size
    inside = (np.abs(on_board[:, 0]) <= w / 2) & (np.abs(on_board[:, 1]) <= h / 2) & (z > 0)
    depth = np.where(inside, z, 0.0).reshape(u.shape)
    return np.repeat(depth[None], 3, axis=0).astype(np.float32), (int(lo[0]), int(lo[1]))


def _observations(rng, count: int, *, depth: bool = True) -> list[Observation]:
    """Board poses facing the camera 0.7-1.1 m away, tilted up to ~35°, over the image."""
    out: list[Observation] = []
    while len(out) < count:
        d = rng.uniform(0.7, 1.1)
        centre = np.array([rng.uniform(-0.45, 0.45) * d, rng.uniform(-0.35, 0.35) * d, d])
        cam_from_board = make_pose([math.pi + rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)], centre)
        px, _ = cv2.projectPoints(apply(cam_from_board, BOARD.inner_corners()), np.zeros(3), np.zeros(3), K_TRUE, D_TRUE)
        px = px.reshape(-1, 2)
        if not ((px > 2).all() and (px[:, 0] < SIZE[0] - 3).all() and (px[:, 1] < SIZE[1] - 3).all()):
            continue
        flange = BASE_FROM_CAMERA @ cam_from_board @ np.linalg.inv(MOUNT)
        detection = Detection(px + rng.normal(scale=0.05, size=px.shape), SIZE)
        frames, origin = _depth_region(cam_from_board, px) if depth else (np.zeros((0, 0, 0), np.float32), (0, 0))
        out.append(Observation("cam", np.zeros(6), flange, detection, None, frames, origin, tilted=False))
    return out


def test_estimation_recovers_pose_lens_and_mount_from_depth_and_pixels():
    obs = _observations(np.random.default_rng(7), 24)
    config = CalibrationConfig(depth_error_terms=())
    estimator = Estimator(BOARD.inner_corners(), config)
    cal = estimator.finish("cam", obs, SensorSpec(True, K_DATASHEET))
    # Clean data: the answers within a millimetre (the mount differs from the design by 5 mm).
    assert np.linalg.norm(cal.base_from_camera[:3, 3] - BASE_FROM_CAMERA[:3, 3]) < 1e-3
    assert angle_deg(cal.base_from_camera, BASE_FROM_CAMERA) < 0.05
    assert np.linalg.norm(cal.flange_from_board[:3, 3] - MOUNT[:3, 3]) < 1e-3
    assert np.abs(cal.depth_K - K_TRUE).max() < 0.5
    assert cal.frames == 24 and cal.depth_reprojection_rms < 0.2


def test_estimation_of_a_colour_only_camera_uses_the_board_poses():
    obs = _observations(np.random.default_rng(8), 20, depth=False)
    cal = Estimator(BOARD.inner_corners(), CalibrationConfig()).finish("cam", obs, SensorSpec(False, K_DATASHEET))
    assert cal.depth_K is None and cal.colour_K is not None
    assert np.linalg.norm(cal.base_from_camera[:3, 3] - BASE_FROM_CAMERA[:3, 3]) < 1e-3
    assert angle_deg(cal.base_from_camera, BASE_FROM_CAMERA) < 0.1
    assert np.linalg.norm(cal.flange_from_board[:3, 3] - MOUNT[:3, 3]) < 1e-3


def test_estimation_needs_three_frames_and_names_the_camera():
    obs = _observations(np.random.default_rng(9), 2)
    with pytest.raises(TooFewFrames, match="'cam'"):
        Estimator(BOARD.inner_corners(), CalibrationConfig()).finish("cam", obs, SensorSpec(True, K_DATASHEET))
