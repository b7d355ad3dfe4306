"""The pose area's errors."""

from __future__ import annotations

from earcore.errors import EarcoreError

__all__ = ["PoseError", "PoseWeightsError"]


class PoseError(EarcoreError):
    """Robot pose from an image failed (no robot model for a type, a fit that did not converge)."""


class PoseWeightsError(PoseError, FileNotFoundError):
    """No usable network weights: none shipped yet, a missing or malformed sidecar."""
