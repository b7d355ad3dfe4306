"""Runs of a sweep (one job per method and seed) in worker processes, one thread each."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context


def run_jobs(one_run: Callable[[dict], str], jobs: list[dict], workers: int) -> None:
    """`one_run(job)` for every job, `workers` at a time (spawned: each opens its own
    torch), printing each job's line as it finishes."""
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        for k, done in enumerate(pool.map(one_run, jobs), 1):
            print(f"[{k}/{len(jobs)}] {done}", flush=True)
