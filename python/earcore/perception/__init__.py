"""The live perception loop: camera frames in, the workspace map (occupancy, danger,
current obstacles) out. See `PerceptionPipeline`."""

from earcore.perception.pipeline import FrameReport, PerceptionPipeline, perturb_pose

__all__ = ["FrameReport", "PerceptionPipeline", "perturb_pose"]
