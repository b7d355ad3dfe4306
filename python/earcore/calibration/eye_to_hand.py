"""Eye-to-hand (Paper I): the camera's pose in the robot's base frame from board corners
seen by the camera (3D, from depth) and placed by forward kinematics.

Unknowns: X = base_from_camera and Z = flange_from_board (the board's mount). For every
frame i and corner c:  X · p_cam(i, c) = F_i · Z · c,  with F_i = base_from_flange.
With Z known, X is one rigid 3D-3D fit over all frames (RANSAC drops bad corners); with
X known, Z is one too (the observed corners carried into the flange frame). Alternating
the two converges to the joint least-squares solution; Z is only fixed when the flange
turned between frames (Paper I tilts the board in place for it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.calibration.errors import DegeneratePoses, TooFewFrames
from earcore.registration import rigid_fit, rigid_fit_ransac

__all__ = ["EyeToHand", "apply_pose", "fit_eye_to_hand", "rotation_spread_deg"]


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
    r0 = poses[0, :3, :3]
    cos = (np.trace(np.einsum("ij,kjl->kil", r0.T, poses[:, :3, :3]), axis1=1, axis2=2) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())


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
    if estimate_mount and rotation_spread_deg(flanges) < min_rotation_deg:
        raise DegeneratePoses(
            camera,
            f"the flange turned by at most {rotation_spread_deg(flanges):.1f}° between frames "
            f"(< {min_rotation_deg}°): the board's mount cannot be told from the camera's pose",
        )
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
