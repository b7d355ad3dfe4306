"""The map demo: a synthetic cell scanned by three depth cameras while an obstacle
(a forearm-sized sphere) sweeps through and leaves; the danger it left behind
decays frame by frame (Paper II, Eq. 1). Writes a PNG and prints one line.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from earcore import DANGER_ON_HIT, OcTree
from earcore.synthetic import render_depth_points
from earcore.transforms import look_at


@dataclass(frozen=True)
class DemoConfig:
    resolution: float = 0.05
    rate_hz: float = 15.0
    #: Seconds the obstacle sweeps through the cell, then seconds it is gone.
    sweep_s: float = 1.5
    after_s: float = 24.0
    danger_alpha: float = 0.3
    out_dir: Path = Path("out")


#: Two Kinect V2-like cameras at ±45° in front of the robot base and one overhead (Paper II).
CAMERAS = {
    "front-left": look_at([1.6, 1.6, 1.4], [0.0, 0.0, 0.5]),
    "front-right": look_at([1.6, -1.6, 1.4], [0.0, 0.0, 0.5]),
    "overhead": look_at([0.05, 0.0, 2.6], [0.0, 0.0, 0.0], up=(1.0, 0.0, 0.0)),
}

#: The static cell: a table (robot base sits on it), a box of parts and a back wall.
BOXES = np.array(
    [
        [-0.5, -0.6, 0.0, 0.5, 0.6, 0.72],  # table
        [0.1, 0.25, 0.72, 0.35, 0.5, 0.9],  # parts box
        [-1.2, -1.5, 0.0, -1.1, 1.5, 2.0],  # back wall
    ]
)


#: Seconds after the obstacle left at which the picture shows the danger it left behind.
SNAPSHOTS_S = (0.5, 10.0, 20.0)


def left_behind(tree: OcTree) -> tuple[np.ndarray, np.ndarray]:
    """Dangerous voxels that no camera hits now (C below the hit value 0.999)."""
    centres, _, values = tree.danger_voxels()
    keep = values < DANGER_ON_HIT
    return centres[keep], values[keep]


def obstacle_centre(t: float, sweep_s: float) -> np.ndarray | None:
    """A forearm sweeping across the table at 0.3 m above it, gone after `sweep_s`."""
    if t > sweep_s:
        return None
    s = t / sweep_s
    return np.array([0.45, -0.7 + 1.4 * s, 1.0])


def show_progress(done: int, total: int) -> None:
    """A bar redrawn in place on a terminal; a line per quarter in logs."""
    if sys.stderr.isatty():
        if done % max(1, total // 60) == 0 or done == total:
            bar = "#" * (30 * done // total)
            print(f"\r  frames [{bar:<30}] {done}/{total}", end="", file=sys.stderr, flush=True)
    elif done * 4 // total != (done - 1) * 4 // total:
        print(f"  frames {done}/{total}", file=sys.stderr, flush=True)


def run(config: DemoConfig = DemoConfig(), progress: bool = True) -> dict:
    tree = OcTree(config.resolution, danger_alpha=config.danger_alpha)
    dt = 1.0 / config.rate_hz
    n_frames = int(round((config.sweep_s + config.after_s) * config.rate_hz))
    start = time.perf_counter()
    max_left = 0
    cleared_at = None
    snapshots: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    history: list[tuple[float, int]] = []
    # Decimated 2×2 (256×212) Kinect V2-like depth, to keep the demo quick.
    camera: dict[str, Any] = dict(width=256, height=212, fx=182.5, fy=182.5, cx=128.0, cy=106.0, max_depth=4.0)
    for i in range(n_frames):
        t = i * dt
        centre = obstacle_centre(t, config.sweep_s)
        spheres = np.empty((0, 4)) if centre is None else np.array([[*centre, 0.12]])
        for pose in CAMERAS.values():
            pts = render_depth_points(pose, spheres, BOXES, 0.0, **camera)
            tree.insert_point_cloud(pts, pose[:3, 3], max_range=4.0)
        report = tree.end_frame(dt)
        after = t - config.sweep_s
        for mark in SNAPSHOTS_S:
            if abs(after - mark) < dt / 2:
                snapshots[mark] = left_behind(tree)
        history.append((t, report.active - report.hit))
        # Danger left behind: dangerous voxels that no camera hit in this frame.
        left = report.active - report.hit
        max_left = max(max_left, left)
        if centre is None and cleared_at is None and left == 0:
            cleared_at = t - config.sweep_s
        if progress:
            show_progress(i + 1, n_frames)
    if progress and sys.stderr.isatty():
        print(file=sys.stderr)
    elapsed = time.perf_counter() - start

    config.out_dir.mkdir(parents=True, exist_ok=True)
    png = config.out_dir / "map_danger.png"
    centres, sizes = tree.occupied_voxels()
    d_centres, _, d_values = tree.danger_voxels()
    draw_map(png, centres, snapshots, np.array(history), config)
    tree.write_binary(config.out_dir / "map.bt")
    summary = {
        "frames": n_frames,
        "cameras": len(CAMERAS),
        "occupied_voxels": int(len(centres)),
        "dangerous_voxels": int(len(d_values)),
        "max_left_behind": int(max_left),
        "cleared_after_s": cleared_at,
        "seconds": elapsed,
        "png": str(png),
    }
    return summary


def draw_map(png: Path, occupied: np.ndarray, snapshots: dict, history: np.ndarray, config: DemoConfig) -> None:
    """Top views at a few moments after the obstacle left (grey: occupied above the
    floor; colour: danger left behind), and the number of such voxels over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(snapshots) + 1, figsize=(4.6 * (len(snapshots) + 1), 4.6), constrained_layout=True)
    above_floor = occupied[occupied[:, 2] > 0.05]
    sc = None
    for ax, (after, (centres, values)) in zip(axes, sorted(snapshots.items())):
        ax.scatter(above_floor[:, 0], above_floor[:, 1], s=5, c="0.8", marker="s")
        sc = ax.scatter(centres[:, 0], centres[:, 1], s=9, c=values, cmap="inferno_r", vmin=0, vmax=1, marker="s")
        ax.set_title(f"{after:g} s after the obstacle left: {len(values)} voxels")
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    if sc is not None:
        fig.colorbar(sc, ax=list(axes[:-1]), label="danger C (Paper II, Eq. 1)", shrink=0.8)
    ax = axes[-1]
    ax.plot(history[:, 0] - config.sweep_s, history[:, 1])
    ax.axvline(0.0, color="0.6", ls="--")
    ax.set_xlabel("seconds after the obstacle left")
    ax.set_ylabel("dangerous voxels not seen occupied")
    ax.set_title(f"danger decay, alpha={config.danger_alpha}, {config.rate_hz:.0f} Hz")
    fig.suptitle(f"earcore map demo: {len(occupied)} occupied voxels at {config.resolution * 100:.0f} cm, {len(CAMERAS)} cameras")
    fig.savefig(png, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from earcore.app.arguments import Parser, positive, seconds

    p = Parser(prog="earcore demo", description=__doc__)
    p.add_argument("--resolution", type=positive, default=DemoConfig.resolution, help="voxel size in metres")
    p.add_argument("--after", type=seconds, default=DemoConfig.after_s, help="seconds simulated after the obstacle left")
    p.add_argument("--out", type=Path, default=DemoConfig.out_dir, help="output folder for the PNG and map.bt")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    s = run(DemoConfig(resolution=args.resolution, after_s=args.after, out_dir=args.out), progress=not args.quiet)
    cleared = "not yet cleared" if s["cleared_after_s"] is None else f"cleared {s['cleared_after_s']:.1f} s after it left"
    print(
        f"earcore demo: {s['cameras']} cameras x {s['frames']} frames in {s['seconds']:.1f} s; "
        f"{s['occupied_voxels']} occupied voxels; the passing obstacle left up to {s['max_left_behind']} dangerous "
        f"voxels, {cleared} (alpha={DemoConfig.danger_alpha}, {DemoConfig.rate_hz:.0f} Hz); wrote {s['png']}"
    )
    return 0
