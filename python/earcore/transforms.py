"""Rigid transforms: the one home of the rotation and pose helpers every area uses.

Poses are 4×4 float64 matrices named `target_from_source`; rotation vectors are
axis × angle (radians); quaternions are (x, y, z, w).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "axis_angle_matrix",
    "look_at",
    "mean_pose",
    "perturb_pose",
    "quaternion",
    "rotation_from_quaternion",
    "pose_from_vector",
    "rotation_angle",
    "rotation_from_vector",
    "rotation_vector",
    "rotation_xyz",
    "turn_from_z",
]


def _skew(axis: np.ndarray) -> np.ndarray:
    return np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])


def axis_angle_matrix(axis, angle: float) -> np.ndarray:
    """The 3×3 rotation by `angle` radians about the unit vector `axis` (Rodrigues)."""
    k = _skew(np.asarray(axis, dtype=np.float64))
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def rotation_from_vector(v) -> np.ndarray:
    """The 3×3 rotation of a rotation vector (axis × angle); the inverse of `rotation_vector`."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3) + _skew(v)
    return axis_angle_matrix(v / angle, angle)


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """Axis × angle of a rotation matrix (angle in [0, π])."""
    r = np.asarray(r, dtype=np.float64)
    cos = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    if np.pi - angle < 1e-6:
        # Near π: the axis is the column of R + I with the largest norm.
        m = r + np.eye(3)
        axis = m[:, np.argmax(np.linalg.norm(m, axis=0))]
        return angle * axis / np.linalg.norm(axis)
    return angle * w / (2 * np.sin(angle))


def rotation_angle(a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray | float:
    """The angle (radians) of rotation `a` (3×3 or 4×4, or a stack of them), or of the
    rotation between `a` and `b` when `b` is given."""
    ra = np.asarray(a, dtype=np.float64)[..., :3, :3]
    if b is not None:
        ra = np.swapaxes(np.asarray(b, dtype=np.float64)[..., :3, :3], -1, -2) @ ra
    cos = (np.trace(ra, axis1=-2, axis2=-1) - 1) / 2
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return float(angle) if np.ndim(angle) == 0 else angle


def pose_from_vector(v) -> np.ndarray:
    """The 4×4 pose of a 6-vector (translation, rotation vector)."""
    v = np.asarray(v, dtype=np.float64).reshape(6)
    m = np.eye(4)
    m[:3, :3] = rotation_from_vector(v[3:])
    m[:3, 3] = v[:3]
    return m


def rotation_xyz(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The 3×3 rotation Rz(yaw) · Ry(pitch) · Rx(roll) (URDF's rpy)."""
    r, p, y = float(roll), float(pitch), float(yaw)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`base_from_camera` (4×4) of a camera at `eye` looking at `target` (z forward, y down)."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: any perpendicular will do
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(z, x), z, eye
    return pose


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2
    x = np.copysign(x, r[2, 1] - r[1, 2])
    y = np.copysign(y, r[0, 2] - r[2, 0])
    z = np.copysign(z, r[1, 0] - r[0, 1])
    return float(x), float(y), float(z), float(w)


def rotation_from_quaternion(wxyz: np.ndarray) -> np.ndarray:
    """3×3 rotations of unit quaternions given scalar first, (w, x, y, z): (..., 4) → (..., 3, 3)
    (`quaternion` gives (x, y, z, w); the dataset's CSV stores w first)."""
    w, x, y, z = np.moveaxis(np.asarray(wxyz, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def turn_from_z(direction) -> tuple[np.ndarray, float]:
    """The shortest turn (unit axis, angle) that carries +z onto `direction` (any
    length > 0); about x when `direction` is ±z."""
    d = np.asarray(direction, dtype=np.float64)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = float(z @ d) / np.linalg.norm(d)
    if np.linalg.norm(v) < 1e-12:
        return np.array([1.0, 0.0, 0.0]), (0.0 if c > 0 else float(np.pi))
    return v / np.linalg.norm(v), float(np.arccos(np.clip(c, -1, 1)))


def perturb_pose(pose: np.ndarray, translation: float, rotation: float, rng: np.random.Generator) -> np.ndarray:
    """A pose moved by `translation` metres and turned by `rotation` radians in random
    directions (to stand in for calibration error)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    r = axis_angle_matrix(axis, rotation)
    shift = rng.normal(size=3)
    out = pose.copy()
    out[:3, :3] = r @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + translation * shift / np.linalg.norm(shift)
    return out


def mean_pose(poses: np.ndarray) -> np.ndarray:
    """The pose (4, 4) closest to all of `poses` (K, 4, 4): mean translation and the
    rotation nearest the mean rotation matrix (the chordal L2 mean)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    u, _, vt = np.linalg.svd(poses[:, :3, :3].mean(axis=0))
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, poses[:, :3, 3].mean(axis=0)
    return out
