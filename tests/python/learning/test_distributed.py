"""Two processes (gloo, CPU) under DDP take the step one process takes on the whole
batch: the training loop's gradients are averaged across processes."""

from __future__ import annotations

import os
import socket
import sys
import time
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
    try:
        for p in procs:
            p.join(timeout=180)
            assert p.exitcode == 0
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
    results = [torch.load(tmp_path / f"rank{r}.pt") for r in range(2)]
    for name, value in single.state_dict().items():
        assert torch.allclose(results[0][name], value, atol=1e-6), name
        assert torch.equal(results[0][name], results[1][name]), name
    # only rank 0 wrote the run's files
    assert (tmp_path / "two" / "checkpoint.pt").is_file()
    start = TinyNet(dropout=0.0)
    assert not torch.allclose(start.state_dict()["body.1.weight"], single.state_dict()["body.1.weight"])


def _leaver(rank: int, port: int, folder: str, case: str) -> None:
    from datetime import timedelta

    import torch.distributed as dist

    from earcore.learning.distributed import shutdown

    os.environ.update({"RANK": str(rank), "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    # A group timeout shorter than the test's wait: a hang shows as a process still running.
    dist.init_process_group("gloo", rank=rank, world_size=2, timeout=timedelta(seconds=150))
    dist.all_reduce(torch.ones(1))
    if rank == 1 and case == "peer-dies":
        os._exit(3)
    if rank == 1 and case == "peer-fails":
        shutdown(together=False)  # its run failed: it leaves at once
        os._exit(1)
    if rank == 0:
        time.sleep(1.0)  # still working (writing the checkpoint) while rank 1 is done
        if case == "peer-fails":
            try:
                dist.all_reduce(torch.ones(1))  # the next training step
            except RuntimeError:
                shutdown(together=False)
                os._exit(4)  # failed at once, not after the group's timeout
        (Path(folder) / "rank0-done").touch()
    shutdown(wait=30.0)
    if rank == 1:
        # Rank 1 left only once rank 0 had finished its work.
        assert (Path(folder) / "rank0-done").is_file()


@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch without torch.distributed")
@pytest.mark.parametrize(("case", "codes"), [("both-finish", [0, 0]), ("peer-dies", [0, 3]), ("peer-fails", [4, 1])])
def test_shutdown_waits_for_the_peer_but_not_for_a_dead_or_failed_one(tmp_path, case, codes):
    ctx = mp.get_context("spawn")
    port = _free_port()
    procs = [ctx.Process(target=_leaver, args=(r, port, str(tmp_path), case)) for r in range(2)]
    for p in procs:
        p.start()
    try:
        deadline = time.monotonic() + 100.0  # within the group's timeout: a hang shows as a process still running
        for p in procs:
            p.join(timeout=max(0.0, deadline - time.monotonic()))
        assert [p.exitcode for p in procs] == codes
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()


@pytest.mark.parametrize(("outcome", "code", "together"), [("ok", 0, True), ("bad-setting", 2, False), ("bad-data", 1, False)])
def test_a_training_command_leaves_the_group_together_only_when_it_succeeded(monkeypatch, outcome, code, together):
    from earcore.errors import ConfigError
    from earcore.learning import distributed
    from earcore.learning.train import run_command

    calls = []
    monkeypatch.setattr(distributed, "shutdown", lambda **kw: calls.append(kw))

    def call():
        if outcome == "bad-setting":
            raise ConfigError("batch_size too large")
        if outcome == "bad-data":
            raise ValueError("the training set is empty")
        return None

    assert run_command("prog", call) == code
    assert calls == [{"together": together}]
