"""earcore vs OctoMap (pyoctomap), side by side on the same data in one run.

The frame is the shared benchmark scene (a 512×424 Kinect V2-like depth frame of a
cell, ~213k points within 3 m; the same frame criterion uses). Both libraries insert
it into an empty tree; the results must be byte-identical (.ot), and the ratio of
median times is printed along with bytes per node. The contenders take turns, one
insertion each per round (OctoMap, earcore on one thread, earcore on two), so a
shared machine whose speed drifts during the run slows all of them alike.

    python benches/bench_vs_octomap.py [--repeats 11]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time

import earcore


def interleaved_medians(contenders: list, repeats: int) -> tuple[list[float], list[object]]:
    """Median time of each `(function, threads)` contender over `repeats` rounds in
    which every contender runs once, in turn; and each one's last result."""
    times: list[list[float]] = [[] for _ in contenders]
    results: list[object] = [None] * len(contenders)
    for round_ in range(repeats + 1):  # round 0 warms up: page faults, thread pool, clocks
        for i, (fn, threads) in enumerate(contenders):
            earcore.set_num_threads(threads)
            start = time.perf_counter()
            results[i] = fn()
            if round_ > 0:
                times[i].append(time.perf_counter() - start)
    earcore.set_num_threads(0)
    return [statistics.median(t) for t in times], results


def main() -> None:
    import pyoctomap

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=11)
    args = parser.parse_args()

    points, origin = earcore.synthetic.benchmark_frame()
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
    print(f"# earcore {earcore.__version__} vs pyoctomap {pyoctomap.__version__ if hasattr(pyoctomap, '__version__') else ''}")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; frame: {len(points)} points; median of {args.repeats} interleaved rounds\n")
    print(
        "| resolution | OctoMap | earcore 1 thread | earcore 2 threads | speed-up 1 thread | speed-up 2 threads | same map "
        "| bytes/node OctoMap | bytes/node earcore |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    tmp = tempfile.mkdtemp()
    for res in (0.05, 0.02):

        def octomap_insert():
            tree = pyoctomap.OcTree(res)
            tree.insertPointCloud(points, origin)
            return tree

        def earcore_insert():
            tree = earcore.OcTree(res)
            tree.insert_point_cloud(points, origin)
            return tree

        (t_ref, t_one, t_two), (ref, ours, _) = interleaved_medians(
            [(octomap_insert, 0), (earcore_insert, 1), (earcore_insert, 2)], args.repeats
        )
        path = os.path.join(tmp, "ours.ot")
        ours.write(path)
        same = open(path, "rb").read() == ref.write()
        print(
            f"| {res * 100:.0f} cm | {t_ref * 1e3:.1f} ms | {t_one * 1e3:.1f} ms | {t_two * 1e3:.1f} ms "
            f"| {t_ref / t_one:.1f}x | {t_ref / t_two:.1f}x | {'yes' if same else 'NO'} "
            f"| {ref.memoryUsage() / ref.size():.1f} | {ours.memory_usage() / ours.size():.1f} |"
        )
        if not same:
            raise SystemExit("maps differ: the comparison is void")


if __name__ == "__main__":
    main()
