"""Point-to-plane ICP side by side, one thread, same data, one run: earcore (against a
`PlaneTarget` and against a 1 cm `SurfaceMap`), small_gicp (its point-to-plane ICP and
its GICP), open3d-cpu (point-to-plane) and kiss-icp (its point-to-point ICP with a
robust kernel against its voxel hash map: `Registration.align_points_to_map`, one
alignment, without the odometry pipeline's motion model and adaptive threshold).

Data: the perception benchmark's frames (four Kinect V2-like cameras in the simulated
cell; back-projected through the sensor's lens with its depth error taken out, into the
robot's base frame by the true poses, cropped to 1.5 m). Target: the
first three cameras' points on a 1 cm voxel grid; source: the fourth camera's points,
15k and 100k of them, moved 2 cm / 2° off. The truth is the identity, so every result
is scored by its remaining error. Target structures (k-d trees, normals, the surface map)
are built once beforehand, as for a map; the times are the alignment alone. earcore runs
least squares (`huber_delta=None`), the point-to-plane peers' objective; its default
kernel is compared in `bench_icp_matrix.py`.

    python benches/bench_icp_vs_peers.py [--repeats 5]

kiss-icp gets the same 5 cm correspondence distance and a Geman-McClure kernel of a
third of it (its odometry's kernel is a third of its adaptive threshold) and its default
convergence criterion; its voxel map keeps up to 20 target points per 1 cm voxel, the
target's spacing (a point searches the 27 voxels around it; 5 cm voxels were 2× slower
and 2× less accurate). It reports no iteration count.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # open3d: one thread, like the others

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import earcore  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from bench_perception import base_points, load_frames  # noqa: E402
from timing import median_time  # noqa: E402


def error(transform: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (degrees) of a transform that should be the identity."""
    cos = np.clip((np.trace(transform[:3, :3]) - 1) / 2, -1.0, 1.0)
    return 1e3 * float(np.linalg.norm(transform[:3, 3])), float(np.degrees(np.arccos(cos)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    import open3d as o3d
    import small_gicp
    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration

    earcore.set_num_threads(1)
    data = load_frames()
    clouds = []
    for i in range(4):
        pts = base_points(data, 0, i)
        clouds.append(earcore.crop(pts, center=np.zeros(3), radius=1.5))
    target = earcore.voxel_downsample(np.vstack(clouds[:3]), 0.01)
    normals = earcore.estimate_normals(target, 20)
    plane_target = earcore.PlaneTarget(target, normals)
    surface = earcore.SurfaceMap(0.01)
    for c in clouds[:3]:
        surface.insert(c)
        surface.insert(c)
    sg_target, sg_tree = small_gicp.preprocess_points(target, downsampling_resolution=0.005, num_neighbors=20)
    kiss_map = VoxelHashMap(voxel_size=0.01, max_distance=100.0, max_points_per_voxel=20)
    kiss_map.add_points(target)
    kiss_registration = Registration(max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=1)  # its defaults
    o3d_target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    o3d_target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    start_pose = np.eye(4)
    start_pose[:3, :3] = o3d.geometry.get_rotation_matrix_from_axis_angle(axis * np.radians(2.0))
    start_pose[:3, 3] = [0.012, -0.01, 0.012]
    rng = np.random.default_rng(0)
    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
    print(f"# point-to-plane ICP, one thread; machine: {cpu}, {os.cpu_count()} cores; target {len(target)} points "
          f"(1 cm grid); source moved {error(start_pose)[0]:.0f} mm / {error(start_pose)[1]:.1f}° off\n")
    print("| source points | method | alignment ms | iterations | ms per iteration | error mm | error ° |")
    print("|---|---|---|---|---|---|---|")
    for n in (15_000, 100_000):
        source = clouds[3][rng.choice(len(clouds[3]), min(n, len(clouds[3])), replace=False)]
        moved = source @ start_pose[:3, :3].T + start_pose[:3, 3]
        back = np.linalg.inv(start_pose)  # the answer: target_from_moved-source
        sg_source = small_gicp.PointCloud(moved)
        small_gicp.estimate_covariances(sg_source, num_neighbors=20)
        o3d_source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(moved))
        rows = []

        def ours(tgt):
            r = earcore.icp_point_to_plane(moved, tgt, np.eye(4), max_correspondence_distance=0.05,
                                           translation_tolerance=1e-5, rotation_tolerance=1e-5, sigma_tolerance=0.0,
                                           huber_delta=None)
            return r.transform, r.iterations

        def sg(kind):
            r = small_gicp.align(sg_target, sg_source, sg_tree, registration_type=kind, max_correspondence_distance=0.05,
                                 num_threads=1, max_iterations=50, rotation_epsilon=1e-5, translation_epsilon=1e-5)
            return r.T_target_source, r.iterations

        def o3d_icp():
            r = o3d.pipelines.registration.registration_icp(
                o3d_source, o3d_target, 0.05, np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPlane(),
                o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=50),
            )
            return np.asarray(r.transformation), None

        def kiss():
            return kiss_registration.align_points_to_map(moved, kiss_map, np.eye(4), 0.05, 0.05 / 3), None

        for label, fn in (("earcore, SurfaceMap", lambda: ours(surface)), ("earcore, PlaneTarget", lambda: ours(plane_target)),
                          ("small_gicp PLANE_ICP", lambda: sg("PLANE_ICP")), ("small_gicp GICP", lambda: sg("GICP")),
                          ("open3d point-to-plane", o3d_icp), ("kiss-icp point-to-point", kiss)):
            seconds, (transform, iterations) = median_time(fn, args.repeats)
            mm, deg = error(np.asarray(transform) @ np.linalg.inv(back))
            per = f"{1e3 * seconds / iterations:.2f}" if iterations else "–"
            rows.append(seconds)
            print(f"| {len(source)} | {label} | {1e3 * seconds:.1f} | {iterations if iterations else '–'} | {per} | {mm:.2f} | {deg:.3f} |")


if __name__ == "__main__":
    main()
