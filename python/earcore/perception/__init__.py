"""The live perception loop: camera frames in, the workspace map (occupancy, danger,
current obstacles) out. See `PerceptionPipeline`."""

from earcore.perception.config import PerceptionConfig
from earcore.perception.pipeline import PerceptionPipeline, PerceptionReport

__all__ = ["PerceptionConfig", "PerceptionPipeline", "PerceptionReport"]
