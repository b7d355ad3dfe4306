"""earcore's robot geometry vs FCL (python-fcl), side by side on the same data in one run.

Scene: the shared work cell (`earcore.synthetic.robot_cell_voxels`, ~18k occupied 5 cm
voxels: floor, walls, a rig plate, a shelf, boxes, a person) and a UR5 whose bodies
are earcore's fitted capsules/cylinders, handed to FCL as the same shapes. Configurations
have the upper arm above the table (shoulder lift in [-π, 0]), the rest uniform in ±π.

* collision: earcore `check_configurations` (batched, one thread) vs FCL, one
  broad-phase `collide` per moving body against a DynamicAABBTree of the voxel boxes
  (the fastest way to use FCL from Python). Both must agree on every configuration.
* clearance: earcore `clearance` vs FCL `distance` per body against the same tree.
* self-filter: earcore `self_filter` on the 213k-point benchmark frame vs the same
  membership test written in numpy.

    python benches/bench_robot_vs_fcl.py [--configs 2000]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

import earcore
import earcore.robots
from timing import median_time


def fcl_objects(model, q):
    import fcl

    placed = model.bodies(q)
    objects = []
    for link, a, b, r, shape in zip(placed["link"], placed["a"], placed["b"], placed["radius"], placed["shape"]):
        if model.fixed_to_root[link]:
            continue
        d = b - a
        length = float(np.linalg.norm(d))
        z = d / length
        helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        geom = fcl.Capsule(r, length) if shape == "capsule" else fcl.Cylinder(r, length)
        objects.append(fcl.CollisionObject(geom, fcl.Transform(np.column_stack([x, np.cross(z, x), z]), (a + b) / 2)))
    return objects


def main() -> None:
    import fcl

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", type=int, default=2000, help="configurations per run")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    earcore.set_num_threads(1)
    model = earcore.robots.load("ur5")
    tree = earcore.OcTree(0.05)
    tree.update_nodes(earcore.synthetic.robot_cell_voxels(0.05, 0))
    centres, sizes = tree.occupied_voxels()
    rng = np.random.default_rng(0)
    qs = model.random_configurations(args.configs, seed=1)
    qs[:, 1] = rng.uniform(-np.pi, 0, len(qs))

    boxes = [fcl.CollisionObject(fcl.Box(s, s, s), fcl.Transform(np.eye(3), c)) for c, s in zip(centres, sizes)]
    manager = fcl.DynamicAABBTreeCollisionManager()
    manager.registerObjects(boxes)
    manager.setup()
    bodies = [fcl_objects(model, q) for q in qs]  # placing shapes is not timed for FCL

    def fcl_collide():
        out = []
        for objects in bodies:
            hit = False
            for obj in objects:
                data = fcl.CollisionData(request=fcl.CollisionRequest())
                manager.collide(obj, data, fcl.defaultCollisionCallback)
                if data.result.is_collision:
                    hit = True
                    break
            out.append(hit)
        return np.array(out)

    def fcl_clearance():
        out = []
        for objects in bodies:
            best = np.inf
            for obj in objects:
                data = fcl.DistanceData()
                manager.distance(obj, data, fcl.defaultDistanceCallback)
                best = min(best, data.result.min_distance)
            out.append(best)
        return np.array(out)

    model.check_configurations(tree, qs[:1])  # build the collision index once (cached)
    t_build, _ = median_time(lambda: earcore.robots.load("ur5").check_configurations(tree, qs[:1]), 3)
    t_ours, hit = median_time(lambda: model.check_configurations(tree, qs, self_collision=False), args.repeats)
    t_fcl, fcl_hit = median_time(fcl_collide, 1)
    free = qs[~hit]
    t_clear, clear = median_time(lambda: model.clearance(tree, free), args.repeats)
    free_bodies = [b for b, h in zip(bodies, hit) if not h]
    bodies_all, bodies = bodies, free_bodies
    t_fcl_clear, fcl_clear = median_time(fcl_clearance, 1)
    bodies = bodies_all

    points, _ = earcore.synthetic.benchmark_frame()
    q = qs[0]
    placed = model.bodies(q)

    def numpy_filter():
        inside = np.zeros(len(points), dtype=bool)
        for a, b, r, shape in zip(placed["a"], placed["b"], placed["radius"], placed["shape"]):
            d = b - a
            t_raw = (points - a) @ d / (d @ d)
            t = np.clip(t_raw, 0, 1)
            near = np.linalg.norm(points - (a + t[:, None] * d), axis=1) <= r
            inside |= near & ((shape == "capsule") | ((t_raw >= 0) & (t_raw <= 1)))
        return ~inside

    t_filter, keep = median_time(lambda: model.self_filter(points, q + 1e-12 * rng.random()), args.repeats)
    t_np_filter, np_keep = median_time(numpy_filter, 3)

    cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
    print(f"# earcore {earcore.__version__} robot geometry vs python-fcl, one thread")
    print(f"# machine: {cpu}, {os.cpu_count()} cores; UR5 ({model.dof} joints, bodies: "
          f"{', '.join(sorted(set(placed['shape'])))}); {len(centres)} occupied voxels at 5 cm; "
          f"{len(qs)} configurations, {hit.mean():.0%} colliding; {len(free)} free for clearance\n")
    print("| operation | earcore | peer | speed-up | agreement |")
    print("|---|---|---|---|---|")
    agree = np.mean(hit == fcl_hit)
    print(f"| collision checks / s | {len(qs) / t_ours:,.0f} | FCL broad-phase: {len(qs) / t_fcl:,.0f} | "
          f"{t_fcl / t_ours:.0f}× | {agree:.2%} same verdict |")
    gap = np.abs(clear["distance"] - fcl_clear)
    print(f"| clearance queries / s | {len(free) / t_clear:,.0f} | FCL distance: {len(free) / t_fcl_clear:,.0f} | "
          f"{t_fcl_clear / t_clear:.0f}× | median gap {np.median(gap) * 1000:.3f} mm, max {gap.max() * 1000:.1f} mm |")
    print(f"| self-filter, {len(points) // 1000}k points | {t_filter * 1000:.2f} ms | numpy: {t_np_filter * 1000:.1f} ms | "
          f"{t_np_filter / t_filter:.0f}× | {np.mean(keep == np_keep):.4%} same |")
    print(f"\ncollision index build (first query on a changed map): {t_build * 1000:.1f} ms")


if __name__ == "__main__":
    main()
