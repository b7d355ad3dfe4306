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


BOARD = np.c_[(np.stack(np.meshgrid(np.arange(8) * 0.03, np.arange(6) * 0.03), -1).reshape(-1, 2) - [0.105, 0.075]), np.zeros(48)]


def flanges_in_view(rng, base_from_camera, mount, frames: int, turn: float) -> np.ndarray:
    """base_from_flange (frames, 4, 4) that put the mounted board 0.6-1.2 m in front of
    the camera, facing it, turned up to `turn` radians about random axes."""
    out = []
    for _ in range(frames):
        depth = rng.uniform(0.6, 1.2)
        camera_from_board = np.eye(4)
        camera_from_board[:3, :3] = cv2.Rodrigues(np.array([np.pi, 0.0, 0.0]) + rng.uniform(-turn, turn, 3))[0]
        camera_from_board[:3, 3] = [rng.uniform(-0.3, 0.3) * depth, rng.uniform(-0.2, 0.2) * depth, depth]
        out.append(base_from_camera @ camera_from_board @ np.linalg.inv(mount))
    return np.array(out)


def corners(flanges, mount) -> np.ndarray:
    poses = flanges @ mount
    return (np.einsum("fij,cj->fci", poses[:, :3, :3], BOARD) + poses[:, None, :3, 3]).reshape(-1, 3)


def test_with_the_mount_estimated_along_the_spread_matches_a_joint_fit():
    """The reference: scipy's least squares fits the pose, the lens and the mount together
    to each noisy draw; the spread of its poses is what the covariance must report."""
    least_squares = pytest.importorskip("scipy.optimize").least_squares
    from earcore.transforms import pose_from_vector

    rng = np.random.default_rng(11)
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    mount = pose_from_vector([0.004, -0.003, 0.1, 0.02, -0.01, 0.03])
    flanges = flanges_in_view(rng, truth, mount, 12, 0.15)
    clean = project(corners(flanges, mount), truth)
    rvec0, _ = cv2.Rodrigues(np.linalg.inv(truth)[:3, :3])
    x0 = np.concatenate([rvec0.ravel(), np.linalg.inv(truth)[:3, 3], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], DIST[[0, 1, 4]], np.zeros(6)])

    def unpack(x):
        k = np.array([[x[6], 0, x[8]], [0, x[7], x[9]], [0, 0, 1.0]])
        d = np.array([x[10], x[11], 0.0, 0.0, x[12]])
        return k, d, mount @ pose_from_vector(x[13:])

    def residual(x, pixels):
        k, d, m = unpack(x)
        px, _ = cv2.projectPoints(corners(flanges, m), x[:3], x[3:6], k, d)
        return px.reshape(-1) - pixels.reshape(-1)

    centre_errors, reported, reported_fixed, per_frame = [], [], [], []
    for _ in range(30):
        pixels = clean + rng.normal(0.0, 0.3, clean.shape)
        x = least_squares(residual, x0, args=(pixels,), method="lm", x_scale="jac").x
        k, d, m = unpack(x)
        pose = np.linalg.inv(pose_from_vector(np.r_[x[3:6], x[:3]]))
        centre_errors.append(pose[:3, 3] - truth[:3, 3])
        points = corners(flanges, m)
        reported.append(pose_uncertainty(points, pixels, k, d, pose, lens_model="radial", mount=(flanges, BOARD, m)).translation_m)
        reported_fixed.append(pose_uncertainty(points, pixels, k, d, pose, lens_model="radial").translation_m)
        per_frame.append(
            pose_uncertainty(points, pixels, k, d, pose, lens_model="radial", mount=(flanges, BOARD, m), corners_per_frame=48).translation_m
        )
    spread = float(np.sqrt((np.array(centre_errors) ** 2).sum(1).mean()))
    # 30 trials pin a standard deviation to about ±13 % (1σ).
    assert 0.7 < spread / np.median(reported) < 1.4, (spread, np.median(reported))
    # The mount's freedom is real here: ignoring it would under-report the spread.
    assert np.median(reported_fixed) < 0.8 * np.median(reported), (np.median(reported_fixed), np.median(reported))
    # Counted per frame (12 frames for 19 unknowns), the leverage correction errs on the
    # cautious side, within bounds.
    assert 0.8 * spread < np.median(per_frame) < 2.0 * spread, (spread, np.median(per_frame))


def test_a_mount_the_frames_cannot_fix_makes_the_pose_uncertain():
    """The flange only translates: a shift of the mount and a shift of the camera look the
    same in every frame, so with the mount free the pose is not known at all."""
    rng = np.random.default_rng(5)
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    mount = np.eye(4)
    mount[2, 3] = 0.1
    flanges = flanges_in_view(rng, truth, mount, 12, 0.0)
    assert np.allclose(flanges[:, :3, :3], flanges[0, :3, :3])
    points = corners(flanges, mount)
    pixels = project(points, truth) + rng.normal(0.0, 0.3, (len(points), 2))
    fixed = pose_uncertainty(points, pixels, K, DIST, truth, lens_model="radial")
    free = pose_uncertainty(points, pixels, K, DIST, truth, lens_model="radial", mount=(flanges, BOARD, mount))
    assert fixed.translation_m < 0.005
    assert free.translation_m > 100 * fixed.translation_m, (fixed.translation_m, free.translation_m)
    assert np.isfinite(fixed.translation_m) and not np.isnan(free.translation_m)


def test_too_few_frames_for_a_per_frame_spread_report_no_certainty():
    """One frame has no spread between frames to measure: "unknown" (infinite), never
    zero; a few frames give a wide, finite answer, wider than the per-pixel one."""
    rng = np.random.default_rng(2)
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    for frames in (1, 4):
        points = rig(rng, truth, frames)
        pixels = project(points, truth) + rng.normal(0.0, 0.3, (len(points), 2))
        u = pose_uncertainty(points, pixels, K, DIST, truth, lens_model="radial", corners_per_frame=48)
        per_pixel = pose_uncertainty(points, pixels, K, DIST, truth, lens_model="radial")
        if frames == 1:
            assert u.translation_m == np.inf and u.rotation_deg == np.inf
        else:
            assert per_pixel.translation_m < u.translation_m < np.inf, (per_pixel.translation_m, u.translation_m)
    with pytest.raises(ValueError, match="whole frames"):
        pose_uncertainty(points, pixels, K, DIST, truth, lens_model="radial", corners_per_frame=47)


@pytest.mark.parametrize(("shared_px", "own_px"), [(0.3, 0.1), (0.0, 0.3)])
def test_errors_shared_by_a_frames_corners_are_counted_per_frame(shared_px, own_px):
    """Each frame's corners shifted together (plus a little independent noise): the
    per-pixel σ² takes the 48 corners as 48 independent looks and under-reports; the
    per-frame (cluster-robust) covariance follows the spread of repeated fits, and still
    does when the noise is independent after all."""
    rng = np.random.default_rng(8)
    frames = 20
    truth = camera_pose(np.array([1.2, 0.8, 1.0]), [0.3, 0.0, 0.3])
    points = rig(rng, truth, frames)
    clean = project(points, truth)
    errors, per_pixel, per_frame = [], [], []
    for _ in range(40):
        shared = np.repeat(rng.normal(0.0, shared_px, (frames, 2)), 48, axis=0)
        pixels = clean + shared + rng.normal(0.0, own_px, clean.shape)
        lens, pose = calibrate_lens_on_robot(points, pixels, SIZE, K * [[1.02], [0.98], [1.0]], None, lens_model="radial")
        errors.append(pose[:3, 3] - truth[:3, 3])
        per_pixel.append(pose_uncertainty(points, pixels, lens.K, lens.distortion, pose, lens_model="radial").translation_m)
        per_frame.append(pose_uncertainty(points, pixels, lens.K, lens.distortion, pose, lens_model="radial", corners_per_frame=48).translation_m)
    spread = float(np.sqrt((np.array(errors) ** 2).sum(1).mean()))
    if shared_px > 0:
        assert np.median(per_pixel) < 0.6 * spread, (spread, np.median(per_pixel))
    assert 0.7 < spread / np.median(per_frame) < 1.4, (spread, np.median(per_frame))

