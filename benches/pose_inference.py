"""Inference time of the pose networks with onnxruntime: each network at the shipped size
(`small`, 128×106) on all cores and at the papers' size (`paper`, 256×212) on one thread,
plus `earcore.pose.estimate` end to end from a Kinect V2 colour image (512×424). The
weights are random (time does not depend on them); prints a markdown table.

    PYTHONPATH=python python benches/pose_inference.py
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from earcore.pose.export import export_network
from earcore.pose.inference import estimate
from earcore.pose.networks import NETWORKS, PRESETS, build_network


def median_ms(run, repeats: int) -> float:
    for _ in range(5):
        run()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        times.append(time.perf_counter() - started)
    return 1e3 * float(np.median(times))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=40)
    args = parser.parse_args()
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), platform.processor())
    print(f"# pose networks with onnxruntime {ort.__version__}; machine: {cpu}, {os.cpu_count()} cores\n")
    print("| network | preset, input | threads | ONNX MB | ms per image | `estimate` from 512×424, ms |")
    print("|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as folder:
        for preset, threads in (("small", os.cpu_count() or 1), ("paper", 1)):
            for name in NETWORKS:
                torch.manual_seed(0)
                options = {**PRESETS[preset], "num_keypoints": 7, "num_robots": 3}
                size = tuple(options.get("input_size", (128, 106)))
                options["input_size"] = list(size)
                network = build_network(name, options).eval()
                path = Path(folder) / f"{name}-{preset}.onnx"
                export_network(network, {"robots": ["ur3", "ur5", "ur10"], "keypoints": {}}, path, check=False)
                session_options = ort.SessionOptions()
                session_options.intra_op_num_threads = threads
                session = ort.InferenceSession(str(path), session_options, providers=["CPUExecutionProvider"])
                image = rng.random((1, 3, size[1], size[0]), dtype=np.float32)
                ms = median_ms(lambda: session.run(None, {"image": image}), args.repeats)
                end_to_end = ""
                if preset == "small":
                    kinect = rng.integers(0, 256, (424, 512, 3), dtype=np.uint8)
                    end_to_end = f"{median_ms(lambda: estimate(kinect, None, path, threads=threads), args.repeats):.2f}"
                mb = path.stat().st_size / 1e6
                print(f"| {name} | {preset}, {size[0]}×{size[1]} | {threads} | {mb:.1f} | {ms:.2f} | {end_to_end} |", flush=True)
    print("\ntargets: shipped network <= 5 ms per image (2 cores); the paper-sized one at 256×212 <= 30 ms on one thread")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
