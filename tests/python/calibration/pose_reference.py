"""Pose helpers the calibration tests share, built on OpenCV (independent of
`earcore.transforms`, which the code under test uses)."""

from __future__ import annotations

import cv2
import numpy as np


def rotation(vector) -> np.ndarray:
    """The 3×3 rotation of a rotation vector (OpenCV's Rodrigues)."""
    r, _ = cv2.Rodrigues(np.asarray(vector, dtype=np.float64))
    return r


def make_pose(rotation_vector, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation(rotation_vector)
    m[:3, 3] = translation
    return m


def apply(m, p):
    """Points (N, 3) carried by the 4×4 transform m."""
    return p @ m[:3, :3].T + m[:3, 3]


def angle_deg(a, b) -> float:
    """The angle (degrees) between the rotations of two poses."""
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1))))


def project(points_cam, K, dist):
    """Pixels (N, 2) of camera-frame points through the lens (K, dist)."""
    px, _ = cv2.projectPoints(points_cam, np.zeros(3), np.zeros(3), K, np.asarray(dist, dtype=np.float64))
    return px.reshape(-1, 2)
