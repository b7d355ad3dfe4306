"""The cell's cameras drawn by the core's rasterizer and by pybullet's tiny renderer,
side by side in one run, over robots, mesh sets and camera placements; with how far
the two images agree.

Each regime builds a simulated cell (seed per regime), moves the robot part-way along a
random joint target and brings the person in, then draws every camera's pinhole render
(before the lens and the noise, which both paths share) with each renderer. Reported
per regime: the median milliseconds per camera frame of each, the ratio, the share of
pixels whose labels agree and the median / 99th-percentile depth difference where they
agree. Placements: the main job's four cameras, Paper I's three calibration cameras,
and three cameras placed at random around the work area (1.0-2.2 m, azimuth ±80°,
elevation 15-60°).

    python benches/bench_render.py [--repeats 5] [--scale 1.0]
"""

from __future__ import annotations

import argparse

import numpy as np

from earcore.sim.camera import opengl_view
from earcore.sim.cell import SimulatedCell
from earcore.sim.config import CameraConfig, CellConfig, calibration_cameras, default_cameras
from timing import median_time


def random_cameras(seed: int) -> list[CameraConfig]:
    rng = np.random.default_rng(seed)
    target = np.array([0.4, 0.0, 0.2])
    cameras = []
    for i, sensor in enumerate(["kinect_v2", "kinect_v1", "f200"]):
        a, e, d = np.radians(rng.uniform(-80, 80)), np.radians(rng.uniform(15, 60)), rng.uniform(1.0, 2.2)
        if sensor == "f200":
            d = rng.uniform(0.7, 1.0)
        position = target + d * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        cameras.append(CameraConfig(f"random_{i}", sensor, tuple(float(x) for x in position), tuple(float(x) for x in target)))
    return cameras


REGIMES = [
    ("ur5, visual meshes, main cameras", dict(robot="ur5", cameras=default_cameras())),
    ("ur5, collision meshes, main cameras", dict(robot="ur5", robot_meshes="collision", cameras=default_cameras())),
    ("ur5, calibration cameras", dict(robot="ur5", cameras=calibration_cameras())),
    ("panda, random cameras", dict(robot="panda", cameras=random_cameras(1))),
    ("iiwa, random cameras", dict(robot="iiwa", cameras=random_cameras(2))),
    ("ur10, random cameras", dict(robot="ur10", cameras=random_cameras(3))),
]


def tiny(cell, cam):
    p, s = cell.p, cam.sensor
    world_from_camera = cam.world_from_base @ cam.base_from_camera
    _, _, _, buffer, seg = p.getCameraImage(s.width, s.height, opengl_view(world_from_camera), cam._projection, renderer=p.ER_TINY_RENDERER)
    buffer = np.reshape(buffer, (s.height, s.width))
    n, f = cam._near, cam._far
    depth = np.where(buffer < 1.0, f * n / (f - (f - n) * buffer), 0.0)
    seg = np.reshape(seg, (s.height, s.width))
    return depth, np.where(seg >= 0, seg & ((1 << 24) - 1), -1)


def raster(cell, cam):
    s = cam.sensor
    world_from_camera = cam.world_from_base @ cam.base_from_camera
    _, depth, label = cell.scene.render(world_from_camera, cam._render_K, s.width, s.height, cam._near, cam._far)
    return depth, label


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--scale", type=float, default=1.0, help="camera_scale of every regime")
    args = parser.parse_args()
    print("| regime | cameras | tiny renderer ms/frame | rasterizer ms/frame | ratio | labels agree | depth diff median / p99 (mm) |")
    print("|---|---|---|---|---|---|---|")
    for k, (name, kwargs) in enumerate(REGIMES):
        cell = SimulatedCell(CellConfig(seed=k, camera_scale=args.scale, **kwargs))
        rng = np.random.default_rng(k)
        lo, hi = cell.model.joint_limits.T
        target = np.clip(cell.q + rng.uniform(-0.8, 0.8, cell.model.dof), lo, hi)
        cell.controller.follow([target])
        for _ in range(int(1.5 / cell.config.time_step)):
            cell.step()
        t_tiny, t_raster, agree, diffs = [], [], [], []
        for cam in cell.cameras:
            raster(cell, cam)  # the meshes are read on the first draw
            a, (zt, lt) = median_time(lambda: tiny(cell, cam), args.repeats)
            b, (zr, lr) = median_time(lambda: raster(cell, cam), args.repeats)
            t_tiny.append(a)
            t_raster.append(b)
            agree.append((lt == lr).mean())
            same = (lt == lr) & (zr > 0)
            diffs.append(np.abs(zr - zt)[same])
        d = np.concatenate(diffs)
        a, b = np.mean(t_tiny), np.mean(t_raster)
        print(
            f"| {name} | {len(cell.cameras)} | {1e3 * a:.1f} | {1e3 * b:.1f} | {a / b:.1f}× | {100 * min(agree):.2f} % (worst camera) | "
            f"{1e3 * np.median(d):.3f} / {1e3 * np.percentile(d, 99):.2f} |",
            flush=True,
        )
        cell.close()


if __name__ == "__main__":
    main()
