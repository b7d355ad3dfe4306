"""The pose uncertainty of the robot-rig lens fit against Monte Carlo: the same rig seen
with fresh pixel noise many times, the spread of the fitted poses against the spread the
fit reports."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from earcore.calibration.intrinsics import calibrate_lens_on_robot, pose_uncertainty  # noqa: E402

K = np.array([[365.0, 0.0, 256.0], [0.0, 365.0, 212.0], [0.0, 0.0, 1.0]])
DIST = np.array([0.09, -0.27, 0.0, 0.0, 0.1])
SIZE = (512, 424)


def camera_pose(eye, target) -> np.ndarray:
    """base_from_camera for a camera at `eye` looking at `target` (OpenCV axes: z
    forward, y down)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
    return m


def rig(rng, base_from_camera, frames: int) -> np.ndarray:
    """Corners (frames × 48, 3) in the base frame: 6 × 8 boards of 3 cm squares, 0.6-1.2 m
    in front of the camera, inside the view, tilted up to 30°."""
    grid = np.stack(np.meshgrid(np.arange(8) * 0.03, np.arange(6) * 0.03), -1).reshape(-1, 2)
    board = np.c_[grid - grid.mean(0), np.zeros(len(grid))]
    out = []
    for _ in range(frames):
        depth = rng.uniform(0.6, 1.2)
        centre = np.array([rng.uniform(-0.4, 0.4) * depth, rng.uniform(-0.3, 0.3) * depth, depth])
        turn, _ = cv2.Rodrigues(rng.uniform(-0.5, 0.5, 3))
        cam = board @ turn.T + centre
        out.append(cam @ base_from_camera[:3, :3].T + base_from_camera[:3, 3])
    return np.vstack(out)


def project(points_base, base_from_camera) -> np.ndarray:
    camera_from_base = np.linalg.inv(base_from_camera)
    rvec, _ = cv2.Rodrigues(camera_from_base[:3, :3])
    px, _ = cv2.projectPoints(points_base, rvec, camera_from_base[:3, 3], K, DIST)
    return px.reshape(-1, 2)


@pytest.mark.parametrize(("frames", "noise_px"), [(20, 0.25), (8, 0.6)])
def test_reported_spread_matches_monte_carlo(frames, noise_px):
    rng = np.random.default_rng(frames)
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    points = rig(rng, truth, frames)
    clean = project(points, truth)
    centre_errors, turn_errors, reported_t, reported_r = [], [], [], []
    for _ in range(40):
        pixels = clean + rng.normal(0.0, noise_px, clean.shape)
        lens, pose = calibrate_lens_on_robot(points, pixels, SIZE, K * [[1.02], [0.98], [1.0]], None, lens_model="radial")
        u = pose_uncertainty(points, pixels, lens.K, lens.distortion, pose, lens_model="radial")
        centre_errors.append(pose[:3, 3] - truth[:3, 3])
        turn, _ = cv2.Rodrigues(pose[:3, :3] @ truth[:3, :3].T)
        turn_errors.append(turn.reshape(3))
        reported_t.append(u.translation_m)
        reported_r.append(u.rotation_deg)
    spread_t = float(np.sqrt((np.array(centre_errors) ** 2).sum(1).mean()))
    spread_r = float(np.degrees(np.sqrt((np.array(turn_errors) ** 2).sum(1).mean())))
    # 40 trials pin a standard deviation to about ±11 % (1σ).
    assert 0.7 < spread_t / np.median(reported_t) < 1.4, (spread_t, np.median(reported_t))
    assert 0.7 < spread_r / np.median(reported_r) < 1.4, (spread_r, np.median(reported_r))


def test_a_degenerate_rig_reports_no_certainty():
    """Corners all on one small patch: the lens and the distance trade off, and the
    pose's spread is large, not small."""
    rng = np.random.default_rng(3)
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    good = rig(rng, truth, 20)
    flat = rig(np.random.default_rng(4), truth, 1)
    flat = np.vstack([flat] * 3)
    for points, expect_small in ((good, True), (flat, False)):
        pixels = project(points, truth) + rng.normal(0.0, 0.25, (len(points), 2))
        lens, pose = calibrate_lens_on_robot(points, pixels, SIZE, K, None, lens_model="radial")
        u = pose_uncertainty(points, pixels, lens.K, lens.distortion, pose, lens_model="radial")
        assert (u.translation_m < 0.003) == expect_small, u.translation_m
