"""earcore's errors: one hierarchy under `EarcoreError`, so `except earcore.EarcoreError`
catches every domain failure the toolkit reports. Shape and dtype mistakes are
`ValueError` / `TypeError`, file-system failures `OSError`, as in numpy.

    EarcoreError
    ├── OutOfMapError        a point outside the octree's addressable cube
    ├── MapFormatError       a .bt / .ot file that is not a valid map
    ├── UrdfError            a robot description that cannot be read (also a ValueError)
    ├── ConfigError          a setting out of its range (also a ValueError)
    ├── PlanningError        earcore.planning: StartInCollision, GoalInCollision,
    │                        NoPathFound, UnreachablePose
    └── CalibrationError     earcore.calibration: BoardNotSeen, TooFewFrames,
                             DegeneratePoses; CalibrationFileError (also a ValueError)

The core's errors are raised by the extension; each area defines its own below the base.
"""

from __future__ import annotations

try:
    from earcore._earcore import EarcoreError, MapFormatError, OutOfMapError
except ImportError:  # the pure-Python parts run without the core; nothing raises the core's errors then

    class EarcoreError(Exception):  # type: ignore[no-redef]
        """Base of every error earcore reports."""

    class OutOfMapError(EarcoreError):  # type: ignore[no-redef]
        """A point outside the octree's addressable cube."""

    class MapFormatError(EarcoreError):  # type: ignore[no-redef]
        """A map file that is not a valid map."""


__all__ = ["ConfigError", "EarcoreError", "MapFormatError", "OutOfMapError", "UrdfError"]


class UrdfError(EarcoreError, ValueError):
    """A URDF file or one of its meshes is malformed, unsupported or missing."""


class ConfigError(EarcoreError, ValueError):
    """A setting (a configuration field, a command-line option) out of its range; the
    message names the setting."""
