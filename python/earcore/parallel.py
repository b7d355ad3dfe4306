"""How many threads the core uses: one process-wide setting (`set_num_threads`) and a
scoped override for the calling thread only (`threads`), for latency-critical steps
whose batches are too small to share out."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from earcore._earcore import get_num_threads, set_local_num_threads, set_num_threads

__all__ = ["get_num_threads", "set_num_threads", "threads"]


@contextmanager
def threads(n: int) -> Iterator[None]:
    """Within the block, the core's calls made from this thread use `n` worker threads
    (1: all on this thread; 0: one per core). Other threads and the process-wide
    setting are unaffected; the previous override comes back on exit.

        with earcore.threads(1):
            robot.check_configurations(tree, qs)
    """
    previous = set_local_num_threads(n)
    try:
        yield
    finally:
        set_local_num_threads(previous)
