"""The port's pose from its triangulated reference points, and refined in both images.

Paper III fits a plane to the triangulated points by least squares (Eqs. 2-3):
z = A·x + B·y + C, whose normal (A, B, −1) is the port's axis. A plane fixes two of the
three rotations; the turn about the axis, which the paper does not recover and which
caused both its failed runs, comes here from the contacts' layout: the measured points,
put in the plane, are turned onto the connector's known layout (a 2D Procrustes fit with
the contacts' identities from the matcher). Beyond the paper, `refine_in_images` fits the
socket's 3D point model to both images at once (six pose parameters, Gauss-Newton with
Levenberg damping on the reprojection error of every reference point in both views).

Poses are `camera_from_port` (left camera); the port frame is the connector's
(`charging.connectors`): origin at the face's centre, z out of the car.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.charging.stereo import StereoRig
from earcore.transforms import rotation_from_vector

__all__ = ["PoseFit", "fit_plane", "plane_normal", "pose_from_points", "refine_in_images"]


@dataclass(frozen=True)
class PoseFit:
    """A fitted `camera_from_port` and its residuals: the points' distance to the model
    (m, RMS) and, after `refine_in_images`, the reprojection error (pixels, RMS)."""

    camera_from_port: np.ndarray
    rms_m: float
    rms_px: float = float("nan")


def fit_plane(points: np.ndarray) -> tuple[float, float, float]:
    """(A, B, C) of the least-squares plane z = A·x + B·y + C (Eqs. 2-3: the three
    normal equations ∂e/∂A = ∂e/∂B = ∂e/∂C = 0 solved together)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"fit_plane: expected at least three points (N, 3), got shape {p.shape}")
    x, y, z = p.T
    n = float(len(p))
    normal_matrix = np.array([[x @ x, x @ y, x.sum()], [x @ y, y @ y, y.sum()], [x.sum(), y.sum(), n]])
    rhs = np.array([x @ z, y @ z, z.sum()])
    if np.linalg.cond(normal_matrix) > 1e12:
        raise ValueError("fit_plane: the points are collinear (or the plane contains the camera's z axis)")
    a, b, c = np.linalg.solve(normal_matrix, rhs)
    return float(a), float(b), float(c)


def plane_normal(a: float, b: float) -> np.ndarray:
    """The unit normal of z = A·x + B·y + C facing the camera (negative z in its frame)."""
    n = np.array([a, b, -1.0])
    return n / np.linalg.norm(n)


def pose_from_points(model: np.ndarray, measured: np.ndarray) -> PoseFit:
    """`camera_from_port` from the connector's reference points (K, 3; in one plane
    z = const of its frame, z facing the camera: the port's face) and the same points
    measured in the camera (K, 3, in the same order): the axis from the plane fit, the
    turn about it from the layout."""
    model, measured = np.asarray(model, float), np.asarray(measured, float)
    if model.shape != measured.shape or model.ndim != 2 or model.shape[1] != 3 or len(model) < 3:
        raise ValueError(f"pose_from_points: expected matching (K >= 3, 3) arrays, got {model.shape} and {measured.shape}")
    if np.ptp(model[:, 2]) > 1e-9:
        raise ValueError("pose_from_points: the model's points must lie in one plane z = const")
    z_axis = plane_normal(*fit_plane(measured)[:2])
    # any in-plane basis, then the layout's turn in it
    helper = np.array([1.0, 0.0, 0.0]) if abs(z_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - z_axis * (helper @ z_axis)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z_axis, e1)
    centre_measured, centre_model = measured.mean(0), model.mean(0)
    d = measured - centre_measured
    u = np.stack([d @ e1, d @ e2], 1)  # measured points in the plane
    v = model[:, :2] - centre_model[:2]  # model points on the face
    # the turn φ taking v onto u (2D Procrustes): maximise Σ u·R(φ)v
    cross = float((v[:, 0] * u[:, 1] - v[:, 1] * u[:, 0]).sum())
    dot = float((v * u).sum())
    phi = np.arctan2(cross, dot)
    x_axis = np.cos(phi) * e1 + np.sin(phi) * e2
    y_axis = np.cross(z_axis, x_axis)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x_axis, y_axis, z_axis], 1)
    pose[:3, 3] = centre_measured - pose[:3, :3] @ centre_model
    fitted = model @ pose[:3, :3].T + pose[:3, 3]
    return PoseFit(pose, float(np.sqrt(((fitted - measured) ** 2).sum(1).mean())))


def _residuals(rig: StereoRig, pose: np.ndarray, model: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    points = model @ pose[:3, :3].T + pose[:3, 3]
    pl, pr = rig.project(points)
    return np.concatenate([(pl - left).ravel(), (pr - right).ravel()])


def _step(pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[:3, :3] = rotation_from_vector(delta[:3]) @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + delta[3:]
    return out


def refine_in_images(rig: StereoRig, start: PoseFit | np.ndarray, model: np.ndarray, left: np.ndarray, right: np.ndarray, *, iterations: int = 20) -> PoseFit:
    """The pose minimising the reprojection error of the model's points (K, 3) onto their
    pixels in the left and right images (K, 2 each), from `start`."""
    pose = np.array(start.camera_from_port if isinstance(start, PoseFit) else start, dtype=np.float64)
    model, left, right = (np.asarray(a, float) for a in (model, left, right))
    if left.shape != (len(model), 2) or right.shape != (len(model), 2):
        raise ValueError(f"refine_in_images: expected (K, 2) pixels for K = {len(model)} points, got {left.shape} and {right.shape}")
    r = _residuals(rig, pose, model, left, right)
    cost, damping = float(r @ r), 1e-3
    for _ in range(iterations):
        jac = np.empty((len(r), 6))
        for k in range(6):
            h = 1e-6 if k < 3 else 1e-6 * max(float(np.linalg.norm(pose[:3, 3])), 1.0)
            delta = np.zeros(6)
            delta[k] = h
            jac[:, k] = (_residuals(rig, _step(pose, delta), model, left, right) - r) / h
        normal = jac.T @ jac
        gradient = jac.T @ r
        improved = False
        for _ in range(10):
            delta = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), -gradient)
            candidate = _step(pose, delta)
            rc = _residuals(rig, candidate, model, left, right)
            if float(rc @ rc) < cost:
                pose, r, improved = candidate, rc, True
                cost, damping = float(rc @ rc), max(damping / 10, 1e-9)
                break
            damping *= 10
        if not improved or np.abs(delta).max() < 1e-10:
            break
    return PoseFit(pose, float("nan"), float(np.sqrt(cost / (len(r) / 2))))
