"""What planning can fail with: every error names the cause, so callers can decide
between a recovery move, a new goal or giving up."""

from __future__ import annotations

from earcore.errors import EarcoreError

__all__ = ["GoalInCollision", "NoPathFound", "PlanningError", "StartInCollision"]


class PlanningError(EarcoreError):
    """Planning could not produce a path."""


class StartInCollision(PlanningError):
    """The start configuration overlaps the map (e.g. an obstacle voxel touches the
    robot): move away first (the reflex's move-away does this)."""

    def __init__(self, message: str, link: str | None = None) -> None:
        super().__init__(message)
        self.link = link


class GoalInCollision(PlanningError):
    """The goal configuration overlaps the map or the robot itself."""

    def __init__(self, message: str, link: str | None = None) -> None:
        super().__init__(message)
        self.link = link


class NoPathFound(PlanningError):
    """No collision-free path within the time budget (the goal may be enclosed)."""

