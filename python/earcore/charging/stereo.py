"""Stereo triangulation for a verging camera pair (Paper III, Eq. 1) and in general.

The paper's pair is two colour cameras fixed to each other "looking slightly inwards"
(turned towards each other about their vertical axes). Its Eq. 1 adds a disparity
offset for the vergence:

    Z0 = b / tan(θ),  Z = b·f / (x1 − x2 + f·b / Z0),  X = x1·Z / f,  Y = y1·Z / f

with (x1, y1), (x2, y2) pixel coordinates from the principal points, f the focal length,
b the baseline and θ the right camera's turn towards the left one. It is a first-order
formula (exact for parallel cameras and on the left axis at the depth Z0 where the
optical axes cross, off elsewhere: about 2 cm at 2 m for the charging cell's 17°
vergence), kept as `verging_triangulation` to reproduce the paper.
`triangulate` is exact for any calibrated pair: the linear (DLT) solution on
undistorted normalised coordinates, each point from both rays.

Frames: OpenCV camera axes (x right, y down, z forward); points come back in the left
camera's frame; `right_from_left` takes left-camera coordinates into the right's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["StereoRig", "project_points", "triangulate", "verging_pose", "verging_rig", "verging_triangulation"]


@dataclass(frozen=True)
class StereoRig:
    """A calibrated pair: intrinsics, lens distortion (OpenCV's k1 k2 p1 p2 k3) and image
    size of each camera, and the right camera's pose from the left's."""

    K_left: np.ndarray
    K_right: np.ndarray
    right_from_left: np.ndarray
    dist_left: np.ndarray = field(default_factory=lambda: np.zeros(5))
    dist_right: np.ndarray = field(default_factory=lambda: np.zeros(5))
    size: tuple[int, int] = (1280, 960)

    @property
    def baseline(self) -> float:
        """Distance between the optical centres (m)."""
        return float(np.linalg.norm(np.linalg.inv(self.right_from_left)[:3, 3]))

    @property
    def vergence_deg(self) -> float:
        """The angle between the two optical axes (degrees)."""
        z = self.right_from_left[:3, :3][:, 2]
        return float(np.degrees(np.arccos(np.clip(z[2], -1.0, 1.0))))

    def project(self, points_left: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) of left-camera points (N, 3) in the left and in the right image."""
        pts = np.asarray(points_left, dtype=np.float64).reshape(-1, 3)
        right = pts @ self.right_from_left[:3, :3].T + self.right_from_left[:3, 3]
        return project_points(pts, self.K_left, self.dist_left), project_points(right, self.K_right, self.dist_right)


def project_points(cam: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of camera-frame points (..., 3) through the pinhole K and OpenCV's
    lens model (k1, k2, p1, p2, k3): cv2.projectPoints without its Jacobians."""
    x = cam[..., 0] / cam[..., 2]
    y = cam[..., 1] / cam[..., 2]
    k1, k2, p1, p2, k3 = (list(np.asarray(dist, dtype=np.float64).ravel()) + [0.0] * 5)[:5]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)


def verging_pose(baseline: float, vergence_deg: float) -> np.ndarray:
    """`left_from_right` of the paper's pair: the right camera `baseline` along the left
    one's x, turned by `vergence_deg` about its vertical (y) axis towards the left one,
    so the optical axes cross at Z0 = baseline / tan(vergence) on the left one's axis."""
    theta = np.radians(vergence_deg)
    # the right camera sits at +x of the left one; turning towards it is a turn about y by −θ
    left_from_right = np.eye(4)
    left_from_right[:3, :3] = np.array([[np.cos(theta), 0.0, -np.sin(theta)], [0.0, 1.0, 0.0], [np.sin(theta), 0.0, np.cos(theta)]])
    left_from_right[:3, 3] = [baseline, 0.0, 0.0]
    return left_from_right


def verging_rig(K: np.ndarray, baseline: float, vergence_deg: float, size: tuple[int, int] = (1280, 960), distortion: np.ndarray | None = None) -> StereoRig:
    """Two equal cameras placed as `verging_pose`: the paper's set-up, Eq. 1's geometry."""
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    return StereoRig(np.asarray(K, float), np.asarray(K, float), np.linalg.inv(verging_pose(baseline, vergence_deg)), dist, dist, size)


def verging_triangulation(left: np.ndarray, right: np.ndarray, f: float, baseline: float, vergence_deg: float, principal: tuple[float, float]) -> np.ndarray:
    """Paper III's Eq. 1: left-camera points (N, 3) from pixel pairs (N, 2) of an ideal
    (undistorted) verging pair with focal length `f` (pixels) and principal point."""
    left, right = np.atleast_2d(np.asarray(left, float)), np.atleast_2d(np.asarray(right, float))
    c = np.asarray(principal, dtype=np.float64)
    x1, y1 = (left - c).T
    x2 = right[:, 0] - c[0]
    theta = np.radians(vergence_deg)
    offset = f * np.tan(theta) if theta else 0.0  # f·b / Z0 with Z0 = b / tan θ
    with np.errstate(divide="ignore", invalid="ignore"):
        z = baseline * f / (x1 - x2 + offset)
    return np.stack([x1 * z / f, y1 * z / f, z], axis=1)


def triangulate(rig: StereoRig, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Left-camera points (N, 3) from matching pixels (N, 2) in the left and right
    images: the two rays' linear (DLT) intersection on undistorted coordinates."""
    import cv2

    left, right = np.atleast_2d(np.asarray(left, float)), np.atleast_2d(np.asarray(right, float))
    if left.shape != right.shape or left.shape[1] != 2:
        raise ValueError(f"triangulate: expected two (N, 2) pixel arrays, got {left.shape} and {right.shape}")
    if not len(left):
        return np.zeros((0, 3))
    a = cv2.undistortPoints(left.reshape(-1, 1, 2), rig.K_left, np.asarray(rig.dist_left, float)).reshape(-1, 2)
    b = cv2.undistortPoints(right.reshape(-1, 1, 2), rig.K_right, np.asarray(rig.dist_right, float)).reshape(-1, 2)
    p1 = np.eye(4)[:3]
    p2 = rig.right_from_left[:3]
    rows = np.stack(
        [a[:, 0:1] * p1[2] - p1[0], a[:, 1:2] * p1[2] - p1[1], b[:, 0:1] * p2[2] - p2[0], b[:, 1:2] * p2[2] - p2[1]], axis=1
    )  # (N, 4, 4): A·X = 0 for the homogeneous point X
    _, _, vt = np.linalg.svd(rows)
    x = vt[:, -1]
    return x[:, :3] / x[:, 3:4]
