"""Registration: point-to-plane ICP (NOctoSLAM Eqs. 6-7) against a target with normals."""

from __future__ import annotations

import warnings

import numpy.typing as npt

from earcore._earcore import IcpResult, PlaneTarget, SurfaceMap, icp_point_to_plane_raw

__all__ = ["DegenerateAlignmentWarning", "IcpResult", "PlaneTarget", "icp_point_to_plane"]


class DegenerateAlignmentWarning(UserWarning):
    """The pairs could not fix all six degrees of freedom (e.g. only one plane seen)."""


def icp_point_to_plane(
    source: npt.ArrayLike,
    target,
    initial: npt.ArrayLike | None = None,
    *,
    max_iterations: int = 50,
    max_correspondence_distance: float = 0.2,
    translation_tolerance: float = 1e-7,
    rotation_tolerance: float = 1e-7,
    huber_delta: float | None = None,
) -> IcpResult:
    """Align `source` points (N, 3) to `target`: a `PlaneTarget` (build it once and
    reuse it), a `(points, normals)` pair, or a `SurfaceMap` (NOctoSLAM's association:
    the leaf's position with its parent's normal, else the deepest node with a normal;
    nodes larger than `max_correspondence_distance` are not paired), from `initial` (4×4
    `target_from_source`, identity by default). Gauss-Newton on the small-angle pose,
    re-orthonormalised every step; `huber_delta` (metres) turns on a Huber kernel.

    Returns an `IcpResult` (transform, rmse, fitness, iterations, converged,
    degenerate, conditioning); warns with `DegenerateAlignmentWarning` when the
    geometry leaves some direction unconstrained.
    """
    if isinstance(target, tuple) and len(target) == 2:
        target = PlaneTarget(*target)
    if not isinstance(target, (PlaneTarget, SurfaceMap)):
        raise TypeError(
            f"target must be a PlaneTarget, a SurfaceMap or a (points, normals) pair, got {type(target).__name__}"
        )
    result = icp_point_to_plane_raw(
        source,
        target,
        initial,
        max_iterations=max_iterations,
        max_correspondence_distance=max_correspondence_distance,
        translation_tolerance=translation_tolerance,
        rotation_tolerance=rotation_tolerance,
        huber_delta=huber_delta,
    )
    if result.degenerate:
        warnings.warn(
            f"ICP is degenerate (conditioning {result.conditioning:.1e}): the scene cannot fix all six degrees of "
            "freedom, the result is unreliable along the unconstrained directions",
            DegenerateAlignmentWarning,
            stacklevel=2,
        )
    return result
