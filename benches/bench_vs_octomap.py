"""earcore vs OctoMap (pyoctomap), side by side on the same data in one run.

The frame is the shared benchmark scene (a 512×424 Kinect V2-like depth frame of a
cell, ~213k points within 3 m; the same frame criterion uses). Both libraries insert
it into an empty tree; the results must be byte-identical (.ot), and the ratio of
median times is printed along with bytes per node.

    python benches/bench_vs_octomap.py [--repeats 11]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time

import numpy as np

import earcore


def median_time(fn, repeats: int) -> tuple[float, object]:
    fn()  # warm-up: page faults, thread pool start, CPU clock ramp
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> None:
    import pyoctomap

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=11)
    args = parser.parse_args()

    points, origin = earcore.synthetic.benchmark_frame()
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
    print(f"# earcore {earcore.__version__} vs pyoctomap {pyoctomap.__version__ if hasattr(pyoctomap, '__version__') else ''}")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; frame: {len(points)} points; median of {args.repeats} runs\n")
    print("| resolution | OctoMap | earcore 1 thread | earcore 2 threads | speed-up 1 thread | speed-up 2 threads | same map | bytes/node OctoMap | bytes/node earcore |")
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

        t_ref, ref = median_time(octomap_insert, args.repeats)
        earcore.set_num_threads(1)
        t_one, ours = median_time(earcore_insert, args.repeats)
        earcore.set_num_threads(2)
        t_two, _ = median_time(earcore_insert, args.repeats)
        earcore.set_num_threads(0)
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
