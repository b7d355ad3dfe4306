"""earcore vs OctoMap (pyoctomap): map insertion over a matrix of scenes, side by side
on the same data in one run.

Scenes (each a list of scans, every scan a point cloud with its sensor origin):
- benchmark: the shared benchmark frame (a 512×424 Kinect V2-like depth frame of a cell,
  ~213k points within 3 m; the frame criterion uses);
- cell: the simulated cell's four Kinect V2 cameras (one frame set, four scans);
- rooms: random rooms of spheres and boxes on a floor, one 512×424 frame each (three
  seeds, ~3 m range);
- outdoor: a depth camera 1.6 m above open ground with boxes and spheres 2-8 m away,
  depth up to 8 m;
- lidar: one sweep of a 64-ring lidar (1024 columns) in NOctoSLAM's 8 × 8 m room;
- close: rooms seen from close by (a camera 0.7-1.2 m from the objects, depth up to
  1.2-2 m, as a wrist or table-side camera sees them), three seeds: short rays, where
  the per-ray costs weigh most.

Each scan set is inserted into an empty tree by OctoMap, by earcore on one thread and
by earcore on two; the maps must be byte-identical (.ot). The contenders take turns,
one insertion each per round; times are medians over rounds, speed-ups medians over
rounds of OctoMap's time over earcore's in the same round (this shared VM's speed
drifts in bursts that hit neighbouring runs alike). Before each insertion the previous
result is dropped and glibc's heap consolidated, outside the clock, so that no
contender pays for freeing another's nodes.

    python benches/bench_vs_octomap.py [--repeats 15] [--scenes benchmark,cell,rooms,outdoor,lidar,close]
"""

from __future__ import annotations

import argparse
import os

# numpy's BLAS threads spin after any call and would take the second core from the
# two-thread runs (and time from the one-thread ones).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import earcore  # noqa: E402
from earcore.synthetic import benchmark_frame, lidar_room, look_at, random_scene, render_depth_points, render_lidar_scan  # noqa: E402

Scan = tuple[np.ndarray, np.ndarray]


def benchmark_scans() -> list[list[Scan]]:
    points, origin = benchmark_frame()
    return [[(points, origin)]]


def cell_scans() -> list[list[Scan]]:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_perception import base_points, load_frames

    data = load_frames()
    return [[(base_points(data, 0, i), data["poses"][0, i][:3, 3].copy()) for i in range(4)]]


def rooms_scans() -> list[list[Scan]]:
    out = []
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        spheres, boxes = random_scene(rng, n_shapes=14, extent=1.6)
        a = rng.uniform(0, 2 * np.pi)
        eye = np.array([2.4 * np.cos(a), 2.4 * np.sin(a), rng.uniform(1.2, 2.0)])
        pose = look_at(eye, np.array([0.0, 0.0, 0.4]))
        out.append([(render_depth_points(pose, spheres, boxes, 0.0, max_depth=3.0), eye)])
    return out


def close_scans() -> list[list[Scan]]:
    out = []
    for seed, distance, depth in ((11, 0.9, 1.5), (12, 1.2, 2.0), (13, 0.7, 1.2)):
        rng = np.random.default_rng(seed)
        spheres, boxes = random_scene(rng, n_shapes=14, extent=1.6)
        a = rng.uniform(0, 2 * np.pi)
        eye = np.array([distance * np.cos(a), distance * np.sin(a), rng.uniform(0.8, 1.4)])
        pose = look_at(eye, np.array([0.0, 0.0, 0.4]))
        out.append([(render_depth_points(pose, spheres, boxes, 0.0, max_depth=depth), eye)])
    return out


def outdoor_scans() -> list[list[Scan]]:
    rng = np.random.default_rng(4)
    n = 30
    r = rng.uniform(2.0, 8.0, n)
    a = rng.uniform(-0.7, 0.7, n)
    centres = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.2, 1.5, n)])
    is_sphere = rng.random(n) < 0.4
    spheres = np.column_stack([centres[is_sphere], rng.uniform(0.15, 0.6, is_sphere.sum())])
    half = rng.uniform(0.1, 0.8, (int((~is_sphere).sum()), 3))
    boxes = np.column_stack([centres[~is_sphere] - half, centres[~is_sphere] + half])
    eye = np.array([0.0, 0.0, 1.6])
    pose = look_at(eye, np.array([6.0, 0.0, 0.3]))
    return [[(render_depth_points(pose, spheres, boxes, 0.0, max_depth=8.0), eye)]]


def lidar_scans() -> list[list[Scan]]:
    rng = np.random.default_rng(5)
    boxes = lidar_room(rng)
    pose = np.eye(4)
    pose[:3, 3] = [0.4, -0.3, 1.8]
    pts = render_lidar_scan(pose, np.zeros((0, 4)), boxes, rings=64, azimuth_steps=1024, vertical_fov_deg=40.0, noise_sigma=0.01)
    return [[(pts + pose[:3, 3], pose[:3, 3].copy())]]


SCENES = {"benchmark": benchmark_scans, "cell": cell_scans, "rooms": rooms_scans, "outdoor": outdoor_scans, "lidar": lidar_scans, "close": close_scans}


def _heap_tidy():
    """One large allocation and its release through glibc's malloc: it consolidates the
    small chunks the last contender freed (its tree's nodes, its hash sets), which the
    next contender's first large allocation would otherwise pay for. (`malloc_trim`
    would consolidate too, but hands pages back that the next contender then faults
    in again.)"""
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = [ctypes.c_void_p]
        return lambda: libc.free(libc.malloc(1 << 16))
    except (OSError, AttributeError):
        return lambda: None


heap_tidy = _heap_tidy()


def interleaved_times(contenders: list, repeats: int) -> tuple[list[list[float]], list[object]]:
    """Times of each `(function, threads)` contender over `repeats` rounds in which
    every contender runs once, in turn; and each one's last result. A contender's
    previous result is dropped and the heap tidied before its clock starts."""
    times: list[list[float]] = [[] for _ in contenders]
    results: list[object] = [None] * len(contenders)
    for round_ in range(repeats + 1):  # round 0 warms up: page faults, thread pool, clocks
        for i, (fn, threads) in enumerate(contenders):
            earcore.set_num_threads(threads)
            results[i] = None
            heap_tidy()
            start = time.perf_counter()
            results[i] = fn()
            if round_ > 0:
                times[i].append(time.perf_counter() - start)
    earcore.set_num_threads(0)
    return times, results


def round_ratio(reference: list[float], ours: list[float]) -> float:
    """Median over rounds of the reference's time over ours in the same round: this
    shared VM's speed drifts in bursts of seconds, which hit neighbouring runs alike."""
    return statistics.median(r / o for r, o in zip(reference, ours))


def main() -> None:
    import pyoctomap

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=15, help="rounds per cell (a third as many where OctoMap takes over a second)")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--resolutions", default="0.05,0.02")
    args = parser.parse_args()

    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
    print(f"# earcore {earcore.__version__} vs pyoctomap {getattr(pyoctomap, '__version__', '')}")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; medians of interleaved rounds\n")
    print(
        "| scene | scans × points | resolution | OctoMap | earcore 1 thread | earcore 2 threads | speed-up 1 thread "
        "| speed-up 2 threads | same map | bytes/node OctoMap | bytes/node earcore | rounds |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    tmp = tempfile.mkdtemp()
    worst = {}
    for scene in args.scenes.split(","):
        sets = SCENES[scene]()
        for k, scans in enumerate(sets):
            name = f"{scene} {k + 1}" if len(sets) > 1 else scene
            scans32 = [(np.ascontiguousarray(p, dtype=np.float64), np.asarray(o, dtype=np.float64)) for p, o in scans]
            for res in map(float, args.resolutions.split(",")):

                def octomap_insert():
                    tree = pyoctomap.OcTree(res)
                    for p, o in scans32:
                        tree.insertPointCloud(p, o)
                    return tree

                def earcore_insert():
                    tree = earcore.OcTree(res)
                    for p, o in scans32:
                        tree.insert_point_cloud(p, o)
                    return tree

                start = time.perf_counter()
                octomap_insert()
                repeats = args.repeats if time.perf_counter() - start < 1.0 else max(3, args.repeats // 3)
                times, (ref, ours, _) = interleaved_times(
                    [(octomap_insert, 0), (earcore_insert, 1), (earcore_insert, 2)], repeats
                )
                t_ref, t_one, t_two = map(statistics.median, times)
                one, two = round_ratio(times[0], times[1]), round_ratio(times[0], times[2])
                # Before `write`, which prunes OctoMap's tree in place. earcore's figure
                # counts everything it holds, spare capacity included.
                bytes_ref, bytes_ours = ref.memoryUsage() / ref.size(), ours.memory_usage() / ours.size()
                path = os.path.join(tmp, "ours.ot")
                ours.write(path)
                same = open(path, "rb").read() == ref.write()
                points = f"{len(scans)} × {round(np.mean([len(p) for p, _ in scans]) / 1000)}k"
                print(
                    f"| {name} | {points} | {res * 100:.0f} cm | {t_ref * 1e3:.1f} ms | {t_one * 1e3:.1f} ms | {t_two * 1e3:.1f} ms "
                    f"| {one:.1f}× | {two:.1f}× | {'yes' if same else 'NO'} | {bytes_ref:.1f} | {bytes_ours:.1f} | {repeats} |",
                    flush=True,
                )
                worst[res] = min(worst.get(res, np.inf), one)
                if not same:
                    raise SystemExit(f"{name} at {res} m: the maps differ, the comparison is void")
    print("\nworst one-thread speed-up: " + ", ".join(f"{100 * r:.0f} cm {w:.1f}×" for r, w in worst.items()))


if __name__ == "__main__":
    main()
