"""The learning area's errors."""

from __future__ import annotations

from earcore.errors import EarcoreError

__all__ = ["DatasetError"]


class DatasetError(EarcoreError, ValueError):
    """A dataset folder, manifest, shard or image that cannot be read as the format
    says; the message names the file."""
