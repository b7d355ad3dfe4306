"""What a dataset worker does with a shard, for every generator (robot and parts images):
keep one renderer (one pybullet world) for its next shard, render the shard's samples
and write them atomically."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from earcore.learning.shards import shard_name, write_shard

__all__ = ["render_shard"]

#: The worker's renderer, keyed by the dataset's options (one at a time).
_RENDERERS: dict[Any, Any] = {}


def render_shard(options: Any, make_renderer: Callable[[Any], Any], specs: Sequence[Any], index: int, folder: str | Path) -> int:
    """Render `specs` (shard `index`) with the worker's renderer for `options` (made by
    `make_renderer` when it has none or one of other options, which is closed) and
    write the shard into `folder`; returns its number of images."""
    renderer = _RENDERERS.get(options)
    if renderer is None:
        for old in _RENDERERS.values():
            old.close()
        _RENDERERS.clear()
        renderer = _RENDERERS[options] = make_renderer(options)
    samples = [renderer.render(spec).sample for spec in specs]
    write_shard(folder, shard_name(index), samples, renderer.header)
    return len(samples)
