"""How many threads the core uses: one process-wide setting (`set_num_threads`) and a
scoped override for the calling thread only (`threads`), for latency-critical steps
whose batches are too small to share out.

The core's thread pool belongs to the process that built it. A child made by
`os.fork` (multiprocessing's default start method on Linux, hence DataLoader workers
and many pipelines) starts a pool of its own on its first parallel call, so earcore
works in forked children after the parent has used it; hooks the extension registers
with `os.register_at_fork` keep the pool's lock free at the instant of the fork.
Other locks still follow fork's usual rule: fork while no other thread is inside an
earcore call on the same object (a map being written by another thread at that
instant stays locked in the child).

Long calls can be stopped with Ctrl-C (`KeyboardInterrupt` within a fraction of a
second) when made from the main thread: ICP (`icp_point_to_plane`, and so
`refine_camera_poses`) between iterations, `estimate_normals` between rounds of
points. An interrupted call returns nothing and changes nothing.
"""

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
