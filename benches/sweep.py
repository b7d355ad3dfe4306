"""Runs of a sweep (one job per method and seed) in worker processes, one thread each,
and the note of the machine that ran them."""

from __future__ import annotations

import os
import platform
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import torch

from earcore.learning.checkpoint import CHECKPOINT_NAME

MACHINE_NOTE = "machine.txt"


def machine() -> str:
    cpu = platform.processor() or "cpu"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    gpu = f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ""
    return f"{cpu}, {os.cpu_count()} cores{gpu}; torch {torch.__version__}, Python {platform.python_version()}"


def run_jobs(one_run: Callable[[dict], str], jobs: list[dict], workers: int, note: Path | None = None) -> int:
    """`one_run(job)` for every job, `workers` at a time (spawned: each opens its own
    torch), printing each job's line as it finishes; a job that raises is reported and
    the others go on. Returns the number that raised. With `note`, the machine is
    written to note/machine.txt first (the report may run elsewhere)."""
    if note is not None:
        Path(note).mkdir(parents=True, exist_ok=True)
        (Path(note) / MACHINE_NOTE).write_text(machine() + "\n")
    failed = 0
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(one_run, job): job for job in jobs}
        for k, done in enumerate(as_completed(futures), 1):
            try:
                line = done.result()
            except Exception as exc:  # one broken run must not lose the sweep
                failed += 1
                line = f"{futures[done].get('out', futures[done])} failed: {type(exc).__name__}: {exc}"
            print(f"[{k}/{len(jobs)}] {line}", flush=True)
    return failed


def claim_run(out: Path, done: tuple[str, ...] = ("results.json",)) -> bool:
    """Whether a sweep's run in `out` is still to do: not when one of the `done` files
    is there; a run that was interrupted (a checkpoint, no result) is removed so it
    starts again, as its curve must be whole."""
    if any((out / name).is_file() for name in done):
        return False
    if (out / CHECKPOINT_NAME).exists():
        shutil.rmtree(out)
    return True


def machine_note(out: Path) -> str:
    """The machine that ran the sweep in `out` (its note), else this one."""
    path = Path(out) / MACHINE_NOTE
    return path.read_text().strip() if path.is_file() else machine()
