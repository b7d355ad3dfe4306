"""Point-to-plane ICP over a matrix of regimes, earcore and its peers side by side in
one run, one thread: the whole alignment (not one iteration), its iterations and its
remaining error.

Scenes: the cell (the perception benchmark's four Kinect V2-like cameras: three make the
target, the fourth the source), random rooms (spheres and boxes on a floor, five depth
cameras of the core's analytic renderer, 1 mm noise; four views target, one source) and a
lidar scan (NOctoSLAM's room walked through with a 64-ring lidar: five scans target, a
later one source). Targets have 30k or 150k points (a voxel grid fine enough, then a
random subset), sources 15k or 60k; the source starts 2 cm / 2° or 10 cm / 10° off
(random axes, seeded); correspondence distance 0.05, 0.2 or 1.0 m. Target structures
(trees, normals, covariances, maps) are built beforehand and not timed.

Two settings per library: matched (every library: the regime's correspondence distance,
least squares, at most 50 iterations, steps below 1e-5 m and 1e-5 rad converge) and
defaults (the regime's correspondence distance, everything else each library's own
default: small_gicp least squares, 20 iterations, 1 mm / 0.1°; earcore's defaults, its
adaptive Huber kernel included). Errors are of the final transform against the truth.

A second table puts open3d's point-to-plane ICP (its own normals, k = 20) and kiss-icp
(point-to-point with a Geman-McClure kernel of a third of the correspondence distance
against its voxel hash map: voxels of the target grid's size but at least 2 cm, up to 20
points each, its default; `Registration.align_points_to_map`, without the odometry
pipeline's motion model and adaptive threshold) beside earcore on the
same alignments. open3d has no step tolerances: matched is at most 50 iterations with its
default relative fitness / RMSE criteria (1e-6), defaults its ICPConvergenceCriteria()
(30 iterations). kiss-icp's criterion is the step's norm: matched 1e-5 and at most 50
iterations, defaults 1e-4 and 500; it is timed once per regime (seconds each), after
an untimed warm-up. Neither reports its iterations. The process is pinned to one core
(open3d's thread pool does not follow OMP_NUM_THREADS).

    python benches/bench_icp_matrix.py [--repeats 3] [--scenes cell,rooms,lidar] [--quick] [--no-others]
"""

from __future__ import annotations

import argparse
import itertools
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
# One core for the whole process: open3d's TBB pool ignores OMP_NUM_THREADS.
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import earcore  # noqa: E402
from earcore.synthetic import handheld_trajectory, lidar_room, look_at, random_scene, render_depth_points, render_lidar_scan  # noqa: E402
from earcore.transforms import axis_angle_matrix  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from timing import median_time  # noqa: E402

MATCHED = dict(max_iterations=50, translation_tolerance=1e-5, rotation_tolerance=1e-5, sigma_tolerance=0.0, huber_delta=None)


def cell_scene(rng):
    from bench_perception import base_points, load_frames

    data = load_frames()
    clouds = [earcore.crop(base_points(data, 0, i), center=np.zeros(3), radius=2.0) for i in range(4)]
    return np.vstack(clouds[:3]), clouds[3]


def rooms_scene(rng):
    spheres, boxes = random_scene(rng, n_shapes=14, extent=1.6)
    views = []
    for k in range(5):
        a = 2 * np.pi * k / 5 + rng.uniform(-0.3, 0.3)
        eye = np.array([2.6 * np.cos(a), 2.6 * np.sin(a), rng.uniform(1.2, 2.0)])
        pts = render_depth_points(look_at(eye, np.array([0.0, 0.0, 0.4])), spheres, boxes, 0.0, max_depth=6.0)
        views.append(pts + rng.normal(0, 0.001, pts.shape))
    return np.vstack(views[:4]), views[4]


def lidar_scene(rng):
    boxes = lidar_room(rng)
    poses = handheld_trajectory(rng, 8.0, rate_hz=2.0)
    scans = []
    for i, pose in enumerate(poses[:6]):  # each scan in its sensor's frame, brought into the room's
        pts = render_lidar_scan(pose, np.zeros((0, 4)), boxes, rings=64, azimuth_steps=1200, noise_sigma=0.005, seed=i)
        scans.append(pts @ pose[:3, :3].T + pose[:3, 3])
    return np.vstack(scans[:5]), scans[5]


SCENES = {"cell": cell_scene, "rooms": rooms_scene, "lidar": lidar_scene}


def subset(points, n, rng):
    return points[rng.choice(len(points), n, replace=False)] if len(points) > n else points


def fine_grid(points, n):
    """A voxel grid with at least `n` points (the coarsest of a few sizes that keeps n;
    the points themselves when none does) and its voxel size (0 for the points)."""
    best, best_size = points, 0.0
    for size in (0.0025, 0.005, 0.01, 0.02, 0.04):
        grid = earcore.voxel_downsample(points, size)
        if len(grid) >= n:
            best, best_size = grid, size
        else:
            break
    return best, best_size


def offset(rng, metres, degrees):
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    m = np.eye(4)
    m[:3, :3] = axis_angle_matrix(axis / np.linalg.norm(axis), np.radians(degrees))
    m[:3, 3] = metres * direction / np.linalg.norm(direction)
    return m


def error(transform):
    cos = np.clip((np.trace(transform[:3, :3]) - 1) / 2, -1.0, 1.0)
    return 1e3 * float(np.linalg.norm(transform[:3, 3])), float(np.degrees(np.arccos(cos)))


class Peers:
    """The target, built once per library."""

    def __init__(self, target, normals, grid_size, others):
        import small_gicp

        self.sg = small_gicp
        self.plane_target = earcore.PlaneTarget(target, normals)
        self.sg_target = small_gicp.PointCloud(target)
        self.sg_tree = small_gicp.KdTree(self.sg_target, num_threads=1)
        small_gicp.estimate_normals_covariances(self.sg_target, self.sg_tree, num_neighbors=20, num_threads=1)
        if others:
            import open3d as o3d
            from kiss_icp.mapping import VoxelHashMap

            self.o3d = o3d
            self.o3d_target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
            self.o3d_target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
            self.kiss_map = VoxelHashMap(voxel_size=max(grid_size, 0.02), max_distance=1e3, max_points_per_voxel=20)
            self.kiss_map.add_points(target)

    def open3d(self, source, radius, matched):
        o3d = self.o3d
        criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50) if matched else o3d.pipelines.registration.ICPConvergenceCriteria()
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
        r = o3d.pipelines.registration.registration_icp(
            cloud, self.o3d_target, radius, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(), criteria
        )
        return np.asarray(r.transformation), 0

    def kiss(self, source, radius, matched):
        from kiss_icp.registration import Registration

        registration = Registration(max_num_iterations=50, convergence_criterion=1e-5, max_num_threads=1) if matched else Registration(500, 1e-4, 1)
        return registration.align_points_to_map(source, self.kiss_map, np.eye(4), radius, radius / 3), 0

    def earcore(self, source, radius, settings):
        r = earcore.icp_point_to_plane(source, self.plane_target, np.eye(4), max_correspondence_distance=radius, **settings)
        return r.transform, r.iterations

    def small_gicp(self, source, radius, kind, settings):
        sg_source = self.sg.PointCloud(source)
        if kind == "GICP":
            self.sg.estimate_covariances(sg_source, num_neighbors=20, num_threads=1)
        extra = {}
        if settings:
            # The step epsilons as earcore's (its sigma test off).
            extra = dict(
                max_iterations=settings["max_iterations"], rotation_epsilon=settings["rotation_tolerance"], translation_epsilon=settings["translation_tolerance"]
            )
        r = self.sg.align(self.sg_target, sg_source, self.sg_tree, registration_type=kind, max_correspondence_distance=radius, num_threads=1, **extra)
        return r.T_target_source, r.iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scenes", default="cell,rooms,lidar")
    parser.add_argument("--quick", action="store_true", help="only the 150k targets, 60k sources")
    parser.add_argument("--no-others", action="store_true", help="small_gicp only (no open3d, kiss-icp)")
    args = parser.parse_args()
    others = []
    earcore.set_num_threads(1)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    print(f"# whole point-to-plane alignments, one thread; {cpu}, {os.cpu_count()} cores\n")
    print(
        "| scene | target | source | offset | radius | earcore matched ms (it, mm/°) | small_gicp PLANE_ICP matched ms (it, mm/°) | ratio | "
        "earcore default ms (it, mm/°) | small_gicp default ms (it, mm/°) | ratio | small_gicp GICP matched ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    worst = {"matched": np.inf, "default": np.inf}
    for scene in args.scenes.split(","):
        rng = np.random.default_rng(7)
        target_all, source_all = SCENES[scene](rng)
        sizes = [(150_000, 60_000)] if args.quick else list(itertools.product((30_000, 150_000), (15_000, 60_000)))
        for n_target, n_source in sizes:
            grid, grid_size = fine_grid(target_all, n_target)
            target = subset(grid, n_target, rng)
            normals = earcore.estimate_normals(target, 20)
            peers = Peers(target, normals, grid_size, not args.no_others)
            source_true = subset(source_all, n_source, rng)
            for (metres, degrees), radius in itertools.product(((0.02, 2.0), (0.10, 10.0)), (0.05, 0.2, 1.0)):
                start = offset(rng, metres, degrees)
                source = source_true @ start[:3, :3].T + start[:3, 3]
                answer = np.linalg.inv(start)
                cells = []
                for name, fn in [
                    ("ours", lambda: peers.earcore(source, radius, MATCHED)),
                    ("plane", lambda: peers.small_gicp(source, radius, "PLANE_ICP", MATCHED)),
                    ("ours default", lambda: peers.earcore(source, radius, {})),
                    ("plane default", lambda: peers.small_gicp(source, radius, "PLANE_ICP", {})),
                    ("gicp", lambda: peers.small_gicp(source, radius, "GICP", MATCHED)),
                ]:
                    try:
                        seconds, (transform, iterations) = median_time(fn, args.repeats)
                        mm, deg = error(np.asarray(transform) @ np.linalg.inv(answer))
                        cells.append((seconds, iterations, mm, deg))
                    except Exception as exc:  # noqa: BLE001 - a refusal is a result
                        cells.append((np.nan, 0, np.nan, np.nan))
                        print(f"<!-- {name}: {type(exc).__name__}: {exc} -->")
                fmt = lambda c: f"{1e3 * c[0]:.1f} ({c[1]}, {c[2]:.2f}/{c[3]:.3f})"  # noqa: E731
                if not args.no_others:
                    row = []
                    for name, fn in [
                        ("open3d", lambda: peers.open3d(source, radius, True)),
                        ("open3d default", lambda: peers.open3d(source, radius, False)),
                        ("kiss-icp", lambda: peers.kiss(source, radius, True)),
                        ("kiss-icp default", lambda: peers.kiss(source, radius, False)),
                    ]:
                        try:
                            # kiss-icp takes seconds: timed once is enough for its ratio.
                            seconds, (transform, _) = median_time(fn, 1 if "kiss" in name else args.repeats)
                            mm, deg = error(np.asarray(transform) @ np.linalg.inv(answer))
                        except Exception as exc:  # noqa: BLE001 - a refusal is a result
                            seconds, mm, deg = np.nan, np.nan, np.nan
                            print(f"<!-- {name}: {type(exc).__name__}: {exc} -->")
                        ours = cells[0 if "default" not in name else 2][0]
                        row.append(f"{1e3 * seconds:.1f} ({mm:.2f}/{deg:.3f}) | {seconds / ours:.2f}×")
                    regime = f"| {scene} | {len(target) // 1000}k | {len(source) // 1000}k | {metres * 100:.0f} cm/{degrees:.0f}° | {radius} | "
                    others.append(regime + " | ".join(row) + " |")
                ratio_m, ratio_d = cells[1][0] / cells[0][0], cells[3][0] / cells[2][0]
                worst["matched"] = min(worst["matched"], ratio_m)
                worst["default"] = min(worst["default"], ratio_d)
                print(
                    f"| {scene} | {len(target) // 1000}k | {len(source) // 1000}k | {metres * 100:.0f} cm/{degrees:.0f}° | {radius} | "
                    f"{fmt(cells[0])} | {fmt(cells[1])} | {ratio_m:.2f}× | {fmt(cells[2])} | {fmt(cells[3])} | {ratio_d:.2f}× | "
                    f"{1e3 * cells[4][0]:.1f} ({cells[4][1]}, {cells[4][2]:.2f}/{cells[4][3]:.3f}) |",
                    flush=True,
                )
    print(f"\nworst ratio small_gicp / earcore: matched {worst['matched']:.2f}×, defaults {worst['default']:.2f}×")
    if others:
        print("\nThe same alignments with open3d and kiss-icp: ms (final error mm / °) and ratio = its time / earcore's (matched / defaults)\n")
        columns = ["open3d matched", "ratio", "open3d default", "ratio", "kiss-icp matched", "ratio", "kiss-icp default", "ratio"]
        print("| scene | target | source | offset | radius | " + " | ".join(columns) + " |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        print("\n".join(others))


if __name__ == "__main__":
    main()
