"""Eye-to-hand (Paper I): the camera's pose in the robot's base frame from board corners
seen by the camera (3D, from depth) and placed by forward kinematics.

Unknowns: X = base_from_camera and Z = flange_from_board (the board's mount). For every
frame i and corner c:  X · p_cam(i, c) = F_i · Z · c,  with F_i = base_from_flange.
With Z known, X is one rigid 3D-3D fit over all frames (RANSAC drops bad corners); with
X known, Z is one too (the observed corners carried into the flange frame). Alternating
the two converges to the joint least-squares solution; Z is only fixed when the flange
turned between frames (Paper I tilts the board in place for it).

A camera without depth sees each frame's board pose A_i = camera_from_board (PnP) instead:
A_i · Z⁻¹ = X⁻¹ · F_i, the AX = ZB problem, solved in closed form by OpenCV's
robot-world/hand-eye calibration (`fit_eye_to_hand_from_poses`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.calibration.errors import DegeneratePoses, TooFewFrames
from earcore.registration import rigid_fit, rigid_fit_ransac
from earcore.transforms import mean_pose, pose_from_vector, rotation_angle

__all__ = [
    "EyeToHand",
    "apply_pose",
    "fit_eye_to_hand",
    "fit_eye_to_hand_from_poses",
    "refine_by_reprojection",
    "rotation_spread_deg",
]


@dataclass
class EyeToHand:
    base_from_camera: np.ndarray
    flange_from_board: np.ndarray
    #: RMS distance (m) between the camera's corners and the robot's, over the inliers.
    rmse: float
    #: Frames and corners used (inliers of the last fit).
    frames: int
    corners: int


def rotation_spread_deg(poses: np.ndarray) -> float:
    """Largest angle (degrees) between the rotation of any pose (K, 4, 4) and the first."""
    return float(np.degrees(rotation_angle(poses, poses[0])).max())


def apply_pose(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) carried by the 4×4 transform `m`."""
    return points @ m[:3, :3].T + m[:3, 3]


def fit_eye_to_hand(
    camera_points: list[np.ndarray],
    base_from_flange: np.ndarray,
    board_points: np.ndarray,
    flange_from_board: np.ndarray,
    *,
    estimate_mount: bool = True,
    threshold: float = 0.01,
    camera: str = "camera",
    min_frames: int = 1,
    min_rotation_deg: float = 10.0,
    iterations: int = 200,
) -> EyeToHand:
    """Fit X (and Z when `estimate_mount`) to frames of corners.

    `camera_points`: per frame, the corners (N, 3) in the camera's frame (NaN rows are
    skipped); `base_from_flange` (F, 4, 4) per frame; `board_points` (N, 3) the corners
    in the board's frame; `flange_from_board` the mount as designed (start and, without
    `estimate_mount`, the answer). Raises `TooFewFrames` and, when the mount is
    estimated from frames that do not turn the flange, `DegeneratePoses`."""
    flanges = np.asarray(base_from_flange, dtype=np.float64).reshape(-1, 4, 4)
    if len(camera_points) != len(flanges):
        raise ValueError(f"{camera}: {len(camera_points)} frames of corners but {len(flanges)} flange poses")
    if len(flanges) < min_frames:
        raise TooFewFrames(camera, len(flanges), min_frames)
    cams, boards, frame_of = [], [], []
    for i, pts in enumerate(camera_points):
        pts = np.asarray(pts, dtype=np.float64)
        ok = np.isfinite(pts).all(axis=1)
        cams.append(pts[ok])
        boards.append(board_points[ok])
        frame_of.append(np.full(ok.sum(), i))
    cam = np.concatenate(cams)
    board = np.concatenate(boards)
    frame = np.concatenate(frame_of)
    if len(cam) < 3:
        raise TooFewFrames(camera, len(flanges), min_frames, "fewer than 3 corners with depth")
    if estimate_mount:
        _check_rotation_variety(flanges, camera, min_rotation_deg)
    z = np.asarray(flange_from_board, dtype=np.float64)
    inliers = np.ones(len(cam), bool)
    x = np.eye(4)
    for it in range(iterations if estimate_mount else 1):
        robot = np.einsum("kij,kj->ki", flanges[frame], np.c_[apply_pose(z, board), np.ones(len(board))])[:, :3]
        x, inliers, rmse = rigid_fit_ransac(cam, robot, threshold, 200, it)
        if inliers.sum() < 12:
            raise DegeneratePoses(
                camera,
                f"only {inliers.sum()} of {len(cam)} corners agree within {1000 * threshold:.0f} mm: the corners, the "
                "lens or the mount are too far off for a rigid fit",
            )
        if not estimate_mount:
            break
        # The camera's corners carried into the flange frame, fitted to the board's.
        seen = apply_pose(x, cam)
        local = np.einsum("kij,kj->ki", np.linalg.inv(flanges)[frame], np.c_[seen, np.ones(len(seen))])[:, :3]
        try:
            z_new = rigid_fit(board[inliers], local[inliers])
        except ValueError as exc:
            raise DegeneratePoses(camera, f"the board's mount cannot be fitted: {exc}") from exc
        step = np.abs(z_new - z).max()
        z = z_new
        if step < 1e-9:
            break
    robot = np.einsum("kij,kj->ki", flanges[frame], np.c_[apply_pose(z, board), np.ones(len(board))])[:, :3]
    residual = np.linalg.norm(apply_pose(x, cam) - robot, axis=1)[inliers]
    return EyeToHand(x, z, float(np.sqrt(np.mean(residual**2))), len(np.unique(frame[inliers])), int(inliers.sum()))


def _check_rotation_variety(flanges: np.ndarray, camera: str, min_rotation_deg: float) -> None:
    spread = rotation_spread_deg(flanges)
    if spread < min_rotation_deg:
        raise DegeneratePoses(
            camera,
            f"the flange turned by at most {spread:.1f}° between frames (< {min_rotation_deg}°): the board's mount cannot be told from the camera's pose",
        )


def fit_eye_to_hand_from_poses(
    camera_from_board: np.ndarray,
    base_from_flange: np.ndarray,
    board_points: np.ndarray,
    *,
    camera: str = "camera",
    min_frames: int = 3,
    min_rotation_deg: float = 10.0,
    method: str = "shah",
) -> EyeToHand:
    """X = base_from_camera and Z = flange_from_board from the board's pose in every
    frame (F, 4, 4; e.g. PnP in a colour-only camera) and the flange's: the AX = ZB
    problem, A_i = camera_from_board_i, B_i = base_from_flange_i, solved by OpenCV's
    `calibrateRobotWorldHandEye` ("shah" or "li": both unknowns at once) or its
    `calibrateHandEye` ("tsai" for Tsai-Lenz, "park", "horaud", "andreff",
    "daniilidis": X from the frames' relative motions, then Z as the mean of
    F_i⁻¹·X·A_i). In OpenCV's names the board is the "world", the robot base the
    "gripper" and the flange the "base". The rmse is the RMS distance between the
    corners where each frame's pose and where the robot put them (it includes the
    pose estimates' error along the view)."""
    from earcore.calibration.board import _cv2

    cv2 = _cv2()
    methods = {"shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH, "li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI}
    relative = {
        "tsai": cv2.CALIB_HAND_EYE_TSAI, "park": cv2.CALIB_HAND_EYE_PARK, "horaud": cv2.CALIB_HAND_EYE_HORAUD,
        "andreff": cv2.CALIB_HAND_EYE_ANDREFF, "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
    }  # fmt: skip
    if method not in methods and method not in relative:
        raise ValueError(f"method must be one of {sorted(methods) + sorted(relative)}, got {method!r}")
    A = np.asarray(camera_from_board, dtype=np.float64).reshape(-1, 4, 4)
    F = np.asarray(base_from_flange, dtype=np.float64).reshape(-1, 4, 4)
    if len(A) != len(F):
        raise ValueError(f"{camera}: {len(A)} board poses but {len(F)} flange poses")
    if not (np.isfinite(A).all() and np.isfinite(F).all()):
        raise ValueError(f"{camera}: the poses must be finite")
    if len(A) < min_frames:
        raise TooFewFrames(camera, len(A), min_frames, "for AX = ZB")
    _check_rotation_variety(F, camera, min_rotation_deg)
    if method in relative:
        # eye-to-hand through the eye-in-hand solver: the flange's inverse poses in, the
        # camera's pose in the base out
        flange_from_base = np.linalg.inv(F)
        r_x, t_x = cv2.calibrateHandEye(
            [f[:3, :3] for f in flange_from_base], [f[:3, 3].reshape(3, 1) for f in flange_from_base],
            [a[:3, :3] for a in A], [a[:3, 3].reshape(3, 1) for a in A], method=relative[method],
        )  # fmt: skip
        x: np.ndarray = np.eye(4)
        x[:3, :3], x[:3, 3] = r_x, np.ravel(t_x)
        z: np.ndarray = mean_pose(flange_from_base @ x @ A)
    else:
        r_board_from_flange, t_board_from_flange, r_camera_from_base, t_camera_from_base = cv2.calibrateRobotWorldHandEye(
            [a[:3, :3] for a in A],
            [a[:3, 3].reshape(3, 1) for a in A],
            [f[:3, :3] for f in F],
            [f[:3, 3].reshape(3, 1) for f in F],
            method=methods[method],
        )
        board_from_flange, camera_from_base = np.eye(4), np.eye(4)
        board_from_flange[:3, :3], board_from_flange[:3, 3] = r_board_from_flange, np.ravel(t_board_from_flange)
        camera_from_base[:3, :3], camera_from_base[:3, 3] = r_camera_from_base, np.ravel(t_camera_from_base)
        x, z = np.linalg.inv(camera_from_base), np.linalg.inv(board_from_flange)
    if not (np.isfinite(x).all() and np.isfinite(z).all()):
        raise DegeneratePoses(camera, "AX = ZB has no solution for these poses")
    seen = np.concatenate([apply_pose(x @ a, board_points) for a in A])
    robot = np.concatenate([apply_pose(f @ z, board_points) for f in F])
    rmse = float(np.sqrt(np.mean(np.sum((seen - robot) ** 2, axis=1))))
    return EyeToHand(x, z, rmse, len(A), len(seen))


def refine_by_reprojection(
    pixels: list[np.ndarray],
    base_from_flange: np.ndarray,
    board_points: np.ndarray,
    K: np.ndarray,
    distortion,
    base_from_camera: np.ndarray,
    flange_from_board: np.ndarray,
    *,
    iterations: int = 30,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The camera pose X and the mount Z that minimise the corners' reprojection error
    through a fixed lens (every frame's corners placed by forward kinematics): damped
    Gauss-Newton on small corrections X·δX, Z·δZ, Jacobian by central differences.
    Returns (X, Z, rms pixels). For a colour-only camera, whose frames carry no depth."""
    from earcore.calibration.board import _cv2

    cv2 = _cv2()
    F = np.asarray(base_from_flange, dtype=np.float64).reshape(-1, 4, 4)
    observed = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in pixels]).ravel()
    counts = [len(np.asarray(p).reshape(-1, 2)) for p in pixels]
    frame = np.repeat(np.arange(len(F)), counts)
    corner = np.concatenate([np.arange(c) for c in counts])
    K, dist = np.asarray(K, dtype=np.float64), np.asarray(distortion, dtype=np.float64)

    def residual(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        camera_from_flange = np.linalg.inv(x) @ F  # (F, 4, 4)
        on_flange = apply_pose(z, board_points)[corner]
        pts = np.einsum("kij,kj->ki", camera_from_flange[frame], np.c_[on_flange, np.ones(len(on_flange))])[:, :3]
        projected, _ = cv2.projectPoints(np.ascontiguousarray(pts), np.zeros(3), np.zeros(3), K, dist)
        return projected.reshape(-1) - observed

    def at(x0, z0, d):
        return x0 @ pose_from_vector(d[:6]), z0 @ pose_from_vector(d[6:])

    x, z = np.asarray(base_from_camera, dtype=np.float64), np.asarray(flange_from_board, dtype=np.float64)
    r = residual(x, z)
    cost, damping, h = float(r @ r), 1e-3, 1e-6
    for _ in range(iterations):
        J = np.empty((len(r), 12))
        for j in range(12):
            e = np.zeros(12)
            e[j] = h
            J[:, j] = (residual(*at(x, z, e)) - residual(*at(x, z, -e))) / (2 * h)
        A, g = J.T @ J, J.T @ r
        while True:
            step = np.linalg.solve(A + damping * np.diag(np.diag(A) + 1e-12), -g)
            nx, nz = at(x, z, step)
            nr = residual(nx, nz)
            if float(nr @ nr) < cost:
                x, z, r, damping = nx, nz, nr, max(damping / 10, 1e-9)
                improvement = cost - float(nr @ nr)
                cost = float(nr @ nr)
                break
            damping *= 10
            if damping > 1e6:
                improvement = 0.0
                break
        if improvement <= 1e-12 * max(cost, 1e-12) or np.abs(step).max() < 1e-10:
            break
    return x, z, float(np.sqrt(cost / (len(r) // 2)))
