"""Registration: point-to-plane ICP (NOctoSLAM Eqs. 6-7) against a target with normals,
and rigid 3D-3D fits of paired points (plain and RANSAC; calibration's eye-to-hand)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from earcore._earcore import (
    IcpResult,
    PlaneTarget,
    SurfaceMap,
    checked_rigid_transform,
    icp_point_to_plane_raw,
    rigid_fit,
    rigid_fit_ransac,
)

__all__ = [
    "DegenerateAlignmentWarning",
    "IcpResult",
    "PlaneTarget",
    "icp_point_to_plane",
    "refine_camera_poses",
    "rigid_fit",
    "rigid_fit_ransac",
]


class DegenerateAlignmentWarning(UserWarning):
    """The pairs could not fix all six degrees of freedom (e.g. only one plane seen)."""


def icp_point_to_plane(
    source: npt.ArrayLike,
    target,
    initial: npt.ArrayLike | None = None,
    *,
    max_iterations: int = 50,
    max_correspondence_distance: float = 0.2,
    translation_tolerance: float = 0.0,
    rotation_tolerance: float = 0.0,
    sigma_tolerance: float = 1.0,
    huber_delta: float | Literal["auto"] | None = "auto",
) -> IcpResult:
    """Align `source` points (N, 3) to `target`: a `PlaneTarget` (build it once and
    reuse it), a `(points, normals)` pair, or a `SurfaceMap` (NOctoSLAM's association:
    the leaf's position with its parent's normal, else the deepest node with a normal;
    nodes larger than `max_correspondence_distance` are not paired), from `initial` (4×4
    `target_from_source`, identity by default). Gauss-Newton on the small-angle pose,
    re-orthonormalised every step.

    `huber_delta` weights the pairs: "auto" (the default) runs least squares until a
    step passes the stopping test below, then Huber's kernel one robust standard
    deviation of the residuals wide (1.4826 × their median magnitude, re-estimated every
    iteration) until a step passes it again, so that pairs on surfaces the target never
    saw (partial overlap) stop pulling the result off; with no stopping test it stays
    least squares. A number is a fixed Huber width in metres from the first iteration;
    None is plain least squares throughout. Under a kernel each step is Newton's on the
    kernel's loss (the curvature of the pairs within the width) where it provably lowers
    the loss, else reweighted least squares'.

    It stops after `max_iterations`, or (with "auto", once the kernel runs) at the first
    step shorter than `sigma_tolerance` standard deviations of the pose estimate (the
    step's Mahalanobis length under the covariance σ²·H⁻¹ of the fit, σ² the pairs'
    residual variance, under a kernel of the residuals clipped to its width: a step the
    data cannot tell from noise), or at the first step
    that moves less than `translation_tolerance` metres and turns less than
    `rotation_tolerance` radians (small_gicp's `translation_epsilon` /
    `rotation_epsilon`, Open3D's step criteria).
    `sigma_tolerance=0` turns the first test off; a zero step tolerance is left out of the
    second (both zero: no step test).

    Returns an `IcpResult` (transform, rmse, fitness, iterations, converged: a test
    stopped it before `max_iterations`, degenerate, conditioning); warns with
    `DegenerateAlignmentWarning` when the geometry leaves some direction unconstrained.

    Each iteration is one pass over the source (O(N) pair lookups); `max_iterations`
    is not capped, but Ctrl-C stops the call between iterations (`KeyboardInterrupt`
    within a fraction of a second, from the main thread).
    """
    if isinstance(target, tuple) and len(target) == 2:
        target = PlaneTarget(*target)
    if not isinstance(target, (PlaneTarget, SurfaceMap)):
        raise TypeError(
            f"target must be a PlaneTarget, a SurfaceMap or a (points, normals) pair, got {type(target).__name__}"
        )
    width: float | None = None
    if isinstance(huber_delta, str):
        if huber_delta != "auto":
            raise ValueError(f'huber_delta must be "auto", a width in metres or None, got {huber_delta!r}')
    else:
        width = huber_delta
    result = icp_point_to_plane_raw(
        source,
        target,
        initial,
        max_iterations=max_iterations,
        max_correspondence_distance=max_correspondence_distance,
        translation_tolerance=translation_tolerance,
        rotation_tolerance=rotation_tolerance,
        sigma_tolerance=sigma_tolerance,
        huber_delta=width,
        adaptive_huber=huber_delta == "auto",
    )
    if result.degenerate:
        warnings.warn(
            f"ICP is degenerate (conditioning {result.conditioning:.1e}): the scene cannot fix all six degrees of "
            "freedom, the result is unreliable along the unconstrained directions",
            DegenerateAlignmentWarning,
            stacklevel=2,
        )
    return result


def refine_camera_poses(
    clouds: Sequence[npt.ArrayLike],
    base_from_cameras: Sequence[npt.ArrayLike],
    *,
    reference: int = 0,
    voxel_size: float = 0.01,
    normal_neighbours: int = 20,
    max_correspondence_distance: float = 0.1,
    huber_delta: float | None = 0.01,
) -> list[np.ndarray]:
    """Paper II's fine alignment of several cameras: each camera's cloud (its own frame)
    is aligned once with point-to-plane ICP to the clouds of the cameras refined before
    it, starting from its calibrated `base_from_camera`. The `reference` camera's pose
    is kept (it fixes the frame). Returns the refined `base_from_camera` poses.

    Reuse the result for later frames until a camera or the robot base moves.

    Cost: per camera, normals of the merged cloud (k = `normal_neighbours`) and one
    ICP of at most 50 iterations; Ctrl-C stops it (`KeyboardInterrupt`).
    """
    from earcore.cloud import estimate_normals, voxel_downsample

    if len(clouds) != len(base_from_cameras) or len(clouds) < 2:
        raise ValueError("give at least two clouds and one base_from_camera pose per cloud")
    if not 0 <= reference < len(clouds):
        raise ValueError(f"reference must name one of the {len(clouds)} cameras (0 to {len(clouds) - 1}), got {reference}")
    poses = [checked_rigid_transform(p, f"base_from_cameras[{i}]") for i, p in enumerate(base_from_cameras)]
    local = [voxel_downsample(c, voxel_size) for c in clouds]
    in_base = lambda i: local[i] @ poses[i][:3, :3].T + poses[i][:3, 3]  # noqa: E731
    done = [reference]
    order = [i for i in range(len(clouds)) if i != reference]
    for i in order:
        merged = voxel_downsample(np.vstack([in_base(j) for j in done]), voxel_size)
        viewpoint = np.mean([poses[j][:3, 3] for j in done], axis=0)
        normals = estimate_normals(merged, normal_neighbours, viewpoint=viewpoint)
        result = icp_point_to_plane(
            local[i],
            PlaneTarget(merged, normals),
            poses[i],
            max_correspondence_distance=max_correspondence_distance,
            huber_delta=huber_delta,
        )
        poses[i] = np.array(result.transform)
        done.append(i)
    return poses
