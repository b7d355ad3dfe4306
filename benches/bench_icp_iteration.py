"""Point-to-plane ICP time per iteration on the perception benchmark's frames: 15k
source points from one Kinect V2-like camera against a 1 cm `SurfaceMap` built from
the other three (NOctoSLAM's association), one thread.

Per iteration = (time of 11 iterations − time of 1) / 10, so the per-call work (Morton
ordering of the source, checks) and the first iteration are reported apart: from the
second iteration on, a source point that stays in its leaf reuses the pair it found
there (most do once the alignment settles), so later iterations are cheaper than the
first. The whole 11-iteration alignment is reported too. Least squares throughout
(`huber_delta=None`): the default kernel starts only once a stopping test passes, which
these fixed iteration counts never ask.

    python benches/bench_icp_iteration.py [--repeats 10]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

import earcore

sys.path.insert(0, str(Path(__file__).parent))
from bench_perception import base_points, load_frames  # noqa: E402
from timing import median_time as median_of  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    data = load_frames()
    earcore.set_num_threads(1)
    clouds = []
    for i in range(4):
        pts = base_points(data, 0, i)
        clouds.append(earcore.crop(pts, center=np.zeros(3), radius=1.5))
    surface = earcore.SurfaceMap(0.01)
    for c in clouds[:3]:
        surface.insert(c)
        surface.insert(c)
    source = clouds[3][np.random.default_rng(0).choice(len(clouds[3]), 15000, replace=False)]
    guess = np.eye(4)
    guess[:3, 3] = [0.01, -0.005, 0.008]

    def median_time(iterations: int) -> float:
        return median_of(
            lambda: earcore.icp_point_to_plane(source, surface, guess, max_iterations=iterations,
                                               max_correspondence_distance=0.05,
                                               translation_tolerance=0.0, rotation_tolerance=0.0, sigma_tolerance=0.0,
                                               huber_delta=None),
            args.repeats,
        )[0]

    one, eleven = median_time(1), median_time(11)
    per_iteration = (eleven - one) / 10
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; one thread")
    print(f"ICP against a 1 cm SurfaceMap, 15k source points: {1e3 * per_iteration:.2f} ms per iteration after the "
          f"first; a call of one iteration {1e3 * one:.2f} ms; 11 iterations {1e3 * eleven:.2f} ms = "
          f"{1e3 * eleven / 11:.2f} ms per iteration, all in (target: <= 1 ms per iteration; NOctoSLAM: 1.8 ms)")


if __name__ == "__main__":
    main()
