"""Planning speed: median time from a planning request to the chosen path
(3 RRT-Connect attempts, simplification, smoothing, Eq. 4 costing) and on to the path
the executive runs with `blend_deviation = 0.1` (corners rounded and checked again), for A→B moves of
a UR5 in the simulated cell's static scene (table, boxes; 5 cm voxels) with a pillar
in the direct path and a danger map beside it, and the share of that time
spent in validity checks (Rust). One thread.

    .venv/bin/python benches/bench_planning.py [--requests 40]
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

import earcore
from earcore.cloud import box_voxel_centres
from earcore.planning import PredictivePlanner

A = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0])
B = np.array([1.3, -1.3, 1.2, -1.5, -1.57, 0.0])


def scene() -> earcore.OcTree:
    from earcore.sim.config import CellConfig

    tree = earcore.OcTree(0.05)

    def box(lo, hi):
        return box_voxel_centres(lo, hi, tree.resolution)

    # The simulated cell's table (clear around the robot's mount), its boxes, a pillar.
    table = box([-0.35, -0.7, -0.04], [1.25, 0.7, 0.0])
    table = table[np.linalg.norm(table[:, :2], axis=1) > 0.25]
    boxes = [box(b[:3], b[3:]) for b in CellConfig().boxes]
    pillar = box([0.28, 0.33, 0.0], [0.38, 0.43, 0.8])
    tree.update_nodes(np.vstack([table, pillar, *boxes]))
    # Danger beside the pillar: hit once, then seen free for a second.
    side = np.array([[x, y, z] for x in (0.15, 0.2) for y in (0.2, 0.25) for z in np.arange(0.3, 0.8, 0.05)])
    tree.insert_point_cloud(side, [0.2, -0.8, 0.5])
    for _ in range(15):
        tree.end_frame(1 / 15)
    return tree


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=40)
    args = parser.parse_args()
    earcore.set_num_threads(1)
    robot = earcore.robots.load("ur5")
    tree = scene()
    starts, goals = [A, B], [B, A]
    usable = [(s, g) for s, g in zip(starts, goals)
              if not robot.check_configurations(tree, np.stack([s, g])).any() and robot.check_motion(tree, s, g)]
    if not usable:
        raise SystemExit("scene: A/B in collision or the direct motion free; adjust the scene")
    totals, plan, optimise, validity, rounding = [], [], [], [], []
    deviation = 0.1  # `[planning] blend_deviation` when turned on (off by default)
    for i in range(args.requests):
        start, goal = usable[i % len(usable)]
        planner = PredictivePlanner(robot, tree, seed=i)
        t0 = time.perf_counter()
        choice = planner.plan(start, goal)
        totals.append(time.perf_counter() - t0)
        t1 = time.perf_counter()
        planner.rrt.rounded(choice.path, deviation)
        rounding.append(time.perf_counter() - t1)
        plan.append(choice.planning_time)
        optimise.append(choice.optimisation_time)
        validity.append(choice.validity_checks["seconds"])
    totals, validity = np.array(totals), np.array(validity)
    print(f"{platform.processor() or platform.machine()}, {args.requests} requests, {len(tree.occupied_voxels()[1])} occupied voxels")
    print(f"time to the chosen path: median {1e3 * np.median(totals):.1f} ms (p90 {1e3 * np.percentile(totals, 90):.1f} ms)")
    print(f"  RRT-Connect {1e3 * np.median(plan):.1f} ms, simplify + smooth + Eq. 4 costing {1e3 * np.median(optimise):.1f} ms (medians)")
    print(f"  validity checks: {100 * np.median(validity / totals):.0f} % of the time (median share)")
    rounding = np.array(rounding)
    print(f"with blend_deviation = {deviation}, rounding the corners and checking again: median {1e3 * np.median(rounding):.1f} ms; "
          f"request to executable path: median {1e3 * np.median(totals + rounding):.1f} ms")


if __name__ == "__main__":
    main()
