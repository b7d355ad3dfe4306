"""Two processes (gloo, CPU) under DDP take the step one process takes on the whole
batch: the training loop's gradients are averaged across processes."""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from earcore.learning.combiners import FixedWeights
from earcore.learning.config import TrainConfig
from earcore.learning.train import train

sys.path.insert(0, str(Path(__file__).parent))
from tiny import TinyNet, TinyObjective, TinySet  # noqa: E402

CONFIG = TrainConfig(
    network="tiny",
    steps=2,
    minutes=None,
    batch_size=8,
    optimiser="sgd",
    momentum=0.0,
    schedule="constant",
    lr_start=0.5,
    lr_end=0.5,
    eval_every_minutes=None,
    threads=1,
)


def _worker(rank: int, world: int, port: int, folder: str) -> None:
    os.environ.update({"RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank), "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    torch.manual_seed(0)
    model = TinyNet(dropout=0.0)
    try:
        train(model, TinyObjective(), TinySet(), CONFIG, folder, combiner=FixedWeights({"joints": 1.0}), progress=False, log=None)
        torch.save(model.state_dict(), Path(folder).parent / f"rank{rank}.pt")
    finally:
        from earcore.learning.distributed import shutdown

        shutdown()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch without torch.distributed")
def test_two_processes_match_one(tmp_path):
    torch.manual_seed(0)
    single = TinyNet(dropout=0.0)
    train(single, TinyObjective(), TinySet(), CONFIG, tmp_path / "one", combiner=FixedWeights({"joints": 1.0}), progress=False, log=None)

    ctx = mp.get_context("spawn")
    port = _free_port()
    procs = [ctx.Process(target=_worker, args=(r, 2, port, str(tmp_path / "two"))) for r in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=180)
        assert p.exitcode == 0
    results = [torch.load(tmp_path / f"rank{r}.pt") for r in range(2)]
    for name, value in single.state_dict().items():
        assert torch.allclose(results[0][name], value, atol=1e-6), name
        assert torch.equal(results[0][name], results[1][name]), name
    # only rank 0 wrote the run's files
    assert (tmp_path / "two" / "checkpoint.pt").is_file()
    start = TinyNet(dropout=0.0)
    assert not torch.allclose(start.state_dict()["body.1.weight"], single.state_dict()["body.1.weight"])


def _leaver(rank: int, port: int, folder: str, dies: bool) -> None:
    import time

    import torch.distributed as dist

    from earcore.learning.distributed import shutdown

    os.environ.update({"RANK": str(rank), "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    dist.init_process_group("gloo", rank=rank, world_size=2)
    dist.all_reduce(torch.ones(1))
    if rank == 1 and dies:
        os._exit(3)
    if rank == 0:
        time.sleep(1.0)  # still working (writing the checkpoint) while rank 1 is done
        (Path(folder) / "rank0-done").touch()
    shutdown(wait=30.0)
    if rank == 1:
        # Rank 1 left only once rank 0 had finished its work.
        assert (Path(folder) / "rank0-done").is_file()


@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch without torch.distributed")
@pytest.mark.parametrize("dies", [False, True], ids=["both-finish", "peer-dies"])
def test_shutdown_waits_for_the_peer_but_not_for_a_dead_one(tmp_path, dies):
    ctx = mp.get_context("spawn")
    port = _free_port()
    procs = [ctx.Process(target=_leaver, args=(r, port, str(tmp_path), dies)) for r in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=120)
    assert [p.exitcode for p in procs] == ([0, 3] if dies else [0, 0])
