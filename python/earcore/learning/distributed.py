"""Multi-process training under torchrun (DDP): the environment torchrun sets is read
here, the process group uses gloo on CPU and NCCL on CUDA, each process sees its
share of every batch, and only rank 0 writes files.

    torchrun --nproc_per_node 2 -m earcore.pose.train --data DIR --out RUN ...
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist

from earcore.errors import ConfigError

__all__ = ["EpochSampler", "World", "all_mean", "init", "shutdown"]


@dataclass(frozen=True)
class World:
    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def main(self) -> bool:
        """The process that writes checkpoints, logs and prints."""
        return self.rank == 0


def from_environment() -> World:
    """The process's place in a torchrun launch (RANK, WORLD_SIZE, LOCAL_RANK), or a world of one."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return World()
    return World(rank=int(os.environ["RANK"]), size=size, local_rank=int(os.environ.get("LOCAL_RANK", "0")))


def init(device: torch.device) -> World:
    """Join the process group when launched by torchrun (gloo for CPU, NCCL for CUDA)."""
    world = from_environment()
    if world.distributed and not dist.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        if device.type == "cuda":
            torch.cuda.set_device(world.local_rank)
        dist.init_process_group(backend=backend, rank=world.rank, world_size=world.size)
    return world


def shutdown(wait: float = 60.0, *, together: bool = True) -> None:
    """Leave the process group. With `together` (this process's run ended well), under
    gloo, first wait for every process to get here: a process that tears its
    connections down while a peer still works (rank 0 writing the checkpoint) can
    abort that peer's gloo threads. Rank 0 waits at most `wait` seconds, the others
    for rank 0 as long as the group's timeout; a peer that has died is noticed at once.
    A process whose run failed leaves at once (`together=False`): waiting there would
    hang peers that are still training until the group's timeout, while its leaving
    makes their next collective fail."""
    if dist.is_available() and dist.is_initialized():
        if together and dist.get_backend() == "gloo":
            try:
                dist.monitored_barrier(timeout=timedelta(seconds=wait))
            except RuntimeError:
                pass  # a peer is gone: leave anyway
        dist.destroy_process_group()


def all_mean(value: torch.Tensor, world: World) -> torch.Tensor:
    """The mean of `value` over the processes (itself in a world of one)."""
    if not world.distributed:
        return value
    value = value.detach().clone()
    dist.all_reduce(value)
    return value / world.size


class EpochSampler:
    """Batches of indices, reshuffled each epoch from (seed, epoch), split across the
    processes like `torch.utils.data.DistributedSampler` (the permutation padded to a
    multiple of the world size, rank r taking every size-th index from r), and able to
    start part-way through an epoch so that a resumed run sees the batches the
    uninterrupted run would have seen. `batch_size` is the global batch: each process
    gets batch_size / world.size of it; a batch larger than the set is a `ConfigError`."""

    def __init__(self, length: int, batch_size: int, seed: int, world: World = World()):
        if length < 1:
            raise ValueError("the training set is empty")
        if batch_size % world.size:
            raise ValueError(f"batch_size {batch_size} must be a multiple of the number of processes {world.size}")
        if batch_size > length:
            raise ConfigError(f"batch_size {batch_size} is larger than the training set ({length} samples); choose a batch of at most {length}")
        self.length, self.batch, self.seed, self.world = length, batch_size, seed, world
        #: whole batches per epoch (the last partial batch is dropped: per-batch class weights need full batches)
        self.per_epoch = length // batch_size

    def position(self, step: int) -> tuple[int, int]:
        """(epoch, batch within the epoch) of optimiser step `step`."""
        return divmod(step, self.per_epoch)

    def epoch_indices(self, epoch: int) -> list[int]:
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
        order = torch.randperm(self.length, generator=g).tolist()
        return order[: self.per_epoch * self.batch]

    def batches(self, start_step: int) -> Iterator[tuple[int, list[int]]]:
        """(epoch, this process's indices) for every step from `start_step` on, forever."""
        epoch, offset = self.position(start_step)
        while True:
            order = self.epoch_indices(epoch)
            for b in range(offset, self.per_epoch):
                chunk = order[b * self.batch : (b + 1) * self.batch]
                yield epoch, chunk[self.world.rank :: self.world.size]
            epoch, offset = epoch + 1, 0
