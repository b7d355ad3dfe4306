"""The main job: the simulated cell end to end. A UR5 shuttles between two poses
(A-B-A) while a person reaches into the workspace; every frame the cameras are
rendered, processed into the map (robot removed, danger decaying), and the result is
written as a rerun recording (out/cell.rrd: cameras, clouds, robot, map coloured by
danger, current obstacles), PNG snapshots of the danger map and a JSON summary.

    earcore run [--config cell.toml] [--duration 30] [--out out] [--camera-scale 1.0]
    earcore config dump > cell.toml        # every option with its default
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from earcore import jsonfile
from earcore.app.arguments import Parser, count, fail, scale, seconds
from earcore.app.config import RunConfig, dump_toml, load_config
from earcore.errors import ConfigError

__all__ = ["GroundTruthScore", "main", "run", "summarize"]


_last_progress = [0.0]


def _progress(done: float, total: float, extra: str = "", *, final: bool = False) -> None:
    """A one-line progress bar on stderr, redrawn at most twice a second (a plain line
    every 10 s when stderr is not a terminal, e.g. a log file)."""
    now = time.perf_counter()
    tty = sys.stderr.isatty()
    if not final and now - _last_progress[0] < (0.5 if tty else 10.0):
        return
    _last_progress[0] = now
    if not tty:
        sys.stderr.write(f"  {done:5.1f}/{total:.1f} s simulated {extra}\n")
        return
    width = 30
    filled = int(width * min(done / total, 1.0))
    sys.stderr.write(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done:5.1f}/{total:.1f} s simulated {extra}")
    sys.stderr.flush()


@dataclass
class GroundTruthScore:
    """What the simulation's ground truth says of a run, frame by frame: how many of the
    robot's own points reached the map, whether the person's arm was in the map
    whenever a camera saw it, and how close the robot came to the person."""

    #: The robot's points (voxel-grid centroids its pixels dominate) that passed every
    #: stage and were inserted, out of those that reached the self-filter.
    robot_points_inserted: int = 0
    robot_points_seen: int = 0
    frames_arm_seen: int = 0
    frames_arm_in_map: int = 0
    min_robot_person_distance: float = float("inf")

    def add_frame(self, cell, pipeline, frames: list, report) -> None:
        self.robot_points_inserted += report.tracked_inserted
        self.robot_points_seen += report.tracked_points
        if cell.person is None:
            return
        seen = any(f.segmentation is not None and np.isin(f.segmentation, cell.person.bodies).sum() > 50 for f in frames)
        if seen:
            self.frames_arm_seen += 1
            hand = cell.person.segments(cell.time)[1][1]  # the wrist
            in_map = pipeline.tree.danger(hand[None])[0] > 0.99 or _near_occupied(pipeline.tree, cell.person.segments(cell.time))
            self.frames_arm_in_map += bool(in_map)
        self.min_robot_person_distance = min(self.min_robot_person_distance, cell.robot_person_distance())


def _build(config: RunConfig, driver):
    """The cell, its perception loop (calibration and the table loaded) and what drives
    the robot: `driver(cell, pipeline)`, the planning executive, or None (a plain A-B-A
    shuttle, planning mode "none")."""
    from earcore.perception import PerceptionPipeline
    from earcore.sim.cell import SimulatedCell, default_waypoints

    cell = SimulatedCell(config.cell)
    fixed = {c.name for c in config.cell.cameras if c.mount == "world"}
    pipeline = PerceptionPipeline(config.perception, cell.model, seed=config.cell.seed, fixed_cameras=fixed)
    pipeline.track_body = cell.robot_id
    if config.perception.calibration:
        from earcore.calibration.store import Calibration

        calibration = Calibration.load(config.perception.calibration)
        unknown = sorted(set(calibration.cameras) - fixed)
        if unknown:
            raise ValueError(f"{config.perception.calibration}: cameras {unknown} are not fixed cameras of this cell ({sorted(fixed)})")
        pipeline.load_calibration(calibration)
    if config.perception.min_height is not None:
        pipeline.add_support(*cell.table_box())
    waypoints = [np.asarray(w, float) for w in config.waypoints] or default_waypoints(config.cell.robot)
    lo, hi = cell.model.joint_limits.T
    for i, w in enumerate(waypoints):
        if w.shape != (cell.model.dof,) or not ((lo <= w) & (w <= hi)).all():
            cell.close()
            raise ConfigError(
                f"waypoints[{i}] must be {cell.model.dof} joint values within the {config.cell.robot}'s limits, got {w.tolist()}"
            )
    executive = None
    if driver is not None:
        executive = driver(cell, pipeline)
    elif config.planning.mode != "none":
        from earcore.planning.executive import Executive

        executive = Executive(
            cell, pipeline, config.planning, waypoints, seed=config.cell.seed, person_distance=cell.robot_person_distance
        )
    return cell, pipeline, executive, waypoints


def _cautions(config: RunConfig) -> list[str]:
    """What makes a run's map or motion mean little, said before it starts."""
    from earcore.sim.sensors import SENSORS

    if not any(SENSORS[c.sensor].has_depth for c in config.cell.cameras):
        blind = " and the robot plans blind" if config.planning.mode != "none" else ""
        return [f"no depth camera in the cell: nothing is mapped{blind}"]
    return []


def run(
    config: RunConfig,
    out: Path,
    *,
    progress: bool = True,
    record: bool = True,
    trips: int | None = None,
    driver=None,
) -> dict:
    """Run the cell for `config.duration` simulated seconds (or until `trips` A-B moves
    are done, if given) and write the outputs to `out`; returns the summary.

    The robot is driven by the planning executive (`config.planning.mode`), by a plain
    A-B-A shuttle (mode "none"), or by `driver(cell, pipeline)`: an object with
    `control(dt)`, `after_step()`, `on_frame()`, `summary()` and `finished` (e.g. the
    Fig. 7 circles in `earcore.app.experiments.planning`)."""
    config.validate()
    out.mkdir(parents=True, exist_ok=True)
    cell, pipeline, executive, waypoints = _build(config, driver)
    cautions = _cautions(config)
    for text in cautions:
        print(f"earcore run: warning: {text}", file=sys.stderr)
    path = waypoints[1:] + waypoints[::-1][1:]
    reports = []
    score = GroundTruthScore()
    snapshots = sorted(config.snapshots)
    written = []
    recorder = None
    if record:
        from earcore.app.recording import Recorder

        recorder = Recorder(out / "cell.rrd")
    watch = None
    if config.pose.camera:
        from earcore.app.pose_watch import PoseWatch

        watch = PoseWatch(config.pose, config.cell.robot)
    started = time.perf_counter()
    render_s = 0.0
    steps = int(round(config.duration / config.cell.time_step))
    pending: dict = {}
    next_map_frame = 0.0
    for _ in range(steps):
        if executive is not None:
            executive.control(config.cell.time_step)
        elif cell.controller.done:
            cell.controller.follow(path)
        cell.step()
        if executive is not None:
            executive.after_step()
            if getattr(executive, "finished", False) or (trips is not None and len(executive.trips) >= trips):
                break
        t0 = time.perf_counter()
        for frame in cell.capture(before=next_map_frame):
            pending[frame.camera] = frame  # a faster camera's newest frame wins
        render_s += time.perf_counter() - t0
        if not pending or cell.time + 1e-9 < next_map_frame:
            continue
        next_map_frame += 1.0 / config.perception.rate_hz
        frames = list(pending.values())
        pending = {}
        report = pipeline.process(frames, cell.q, cell.time)
        reports.append(report)
        if executive is not None:
            executive.on_frame()
        if recorder is not None:
            recorder.log_frame(cell.time, cell, pipeline, frames, report, executive)
        score.add_frame(cell, pipeline, frames, report)
        if watch is not None:
            picture = watch.observe(cell.time, cell, frames)
            if picture is not None and recorder is not None:
                recorder.log_pose(cell.time, config.pose.camera, picture)
        while snapshots and cell.time >= snapshots[0]:
            written.append(str(draw_snapshot(out / f"danger_{snapshots.pop(0):05.1f}s.png", pipeline, cell)))
        if progress:
            moves = f" | {len(executive.trips)}/{trips} moves" if trips is not None and executive is not None else ""
            _progress(cell.time, config.duration, f"| perception {1e3 * report.total:.0f} ms/frame{moves}")
    if progress:
        _progress(cell.time, config.duration, "", final=True)
        if sys.stderr.isatty():
            sys.stderr.write("\n")
    summary = summarize(config, cell, pipeline, reports, score)
    summary["wall_s"] = round(time.perf_counter() - started, 2)
    summary["render_s"] = round(render_s, 2)
    summary["snapshots"] = written
    if cautions:
        summary["warnings"] = cautions
    if executive is not None:
        summary["planning"] = executive.summary()
        summary["trips"] = [t.as_dict() for t in getattr(executive, "trips", [])]
    if watch is not None:
        summary["pose"] = watch.summary()
        png = watch.save_last(out / "pose.png")
        if png is not None:
            summary["pose"]["picture"] = str(png)
    if recorder is not None:
        recorder.close()
        summary["recording"] = str(recorder.path)
    (out / "summary.json").write_text(jsonfile.dumps(summary, indent=2))
    cell.close()
    return summary


def summarize(config: RunConfig, cell, pipeline, reports: list, score: GroundTruthScore) -> dict:
    """The run's summary: frames, per-stage perception timings, the map, the ground truth's verdicts."""
    timings = {s: [r.timings.get(s, 0.0) for r in reports] for s in reports[0].timings} if reports else {}
    danger = pipeline.tree.danger_voxels()[2]
    seen = score.robot_points_seen
    return {
        "config": asdict(config),
        "frames": len(reports),
        "simulated_s": cell.time,
        "perception_ms_per_frame": {
            s: {"mean": round(1e3 * float(np.mean(v)), 3), "p95": round(1e3 * float(np.percentile(v, 95)), 3)}
            for s, v in timings.items()
        },
        "perception_ms_total_mean": round(1e3 * float(np.mean([r.total for r in reports])), 3) if reports else 0.0,
        "points_in_per_frame": int(np.mean([r.points_in for r in reports])) if reports else 0,
        "occupied_voxels": int(len(pipeline.tree.occupied_voxels()[1])),
        "danger_voxels": int(len(danger)),
        "danger_mean": float(danger.mean()) if len(danger) else 0.0,
        "robot_points_reaching_map": score.robot_points_inserted,
        "robot_points_seen": seen,
        "robot_points_leak_fraction": score.robot_points_inserted / seen if seen else 0.0,
        "frames_arm_seen": score.frames_arm_seen,
        "frames_arm_in_map": score.frames_arm_in_map,
        "min_robot_person_distance_m": score.min_robot_person_distance,
    }


def _near_occupied(tree, segments) -> bool:
    """Whether the map holds an occupied voxel within 5 cm of the arm's capsules."""
    points = []
    for a, b, _ in segments:
        for t in np.linspace(0, 1, 6):
            points.append(a + t * (b - a))
    occupied = tree.is_occupied(np.array(points))
    return bool((occupied == 1).any())


def draw_snapshot(png: Path, pipeline, cell) -> Path:
    """Top and side views of the map: occupied voxels grey, dangerous ones coloured by
    danger, the robot's bodies and the person's arm (ground truth) as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import PowerNorm

    tree = pipeline.tree
    centres, _ = tree.occupied_voxels()
    dcentres, _, dvalues = tree.danger_voxels()
    # Colour only the danger left behind: dangerous voxels seen free now (what is
    # there now is the map itself, in grey). Eq. 1 keeps C above 0.9 for ~15 s and then
    # drops it fast, so the colour scale stretches the top of the range.
    fading = tree.is_occupied(dcentres) == 0 if len(dcentres) else np.zeros(0, bool)
    dcentres, dvalues = dcentres[fading], dvalues[fading]
    bodies = cell.model.bodies(cell.q)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.5))
    for ax, (i, j, label) in zip(axes, [(0, 1, "top view (x, y), above the table"), (0, 2, "side view (x, z)")]):
        near = np.linalg.norm(centres - cell.model.base[:3, 3], axis=1) < pipeline.config.crop_radius
        shown = np.ones(len(dcentres), bool)
        if j == 1:
            # From above, skip the table layer and the voxel row on it (whose cells the
            # table's free rays and the objects' lowest points share, so they flicker).
            near &= centres[:, 2] > pipeline.tree.resolution
            shown = dcentres[:, 2] > pipeline.tree.resolution
        ax.scatter(centres[near, i], centres[near, j], s=5, c="0.55", marker="s", linewidths=0, label="occupied now")
        order = np.flatnonzero(shown)[np.argsort(dvalues[shown])]
        sc = ax.scatter(
            dcentres[order, i], dcentres[order, j], s=7, c=dvalues[order], cmap="YlOrRd",
            norm=PowerNorm(gamma=6, vmin=0, vmax=1), marker="s", linewidths=0,
        )
        for a, b, r in zip(bodies["a"], bodies["b"], bodies["radius"]):
            ax.plot([a[i], b[i]], [a[j], b[j]], color="tab:blue", lw=max(1.0, r * 60), alpha=0.6, solid_capstyle="round")
        for a, b, r in cell.person_segments():
            ax.plot([a[i], b[i]], [a[j], b[j]], color="tab:green", lw=max(1.0, r * 60), alpha=0.5, ls="--")
        ax.set_title(label)
        ax.set_aspect("equal")
        ax.set_xlim(-0.8, 1.5)
        ax.set_ylim(-1.0, 1.2) if j == 1 else ax.set_ylim(-0.2, 1.4)
    fig.colorbar(sc, ax=axes, label="danger C (Eq. 1)", shrink=0.8, ticks=[0.5, 0.8, 0.9, 0.95, 0.99])
    fig.suptitle(f"t = {cell.time:.1f} s: occupied now (grey), danger left behind (colour), robot bodies (blue), person's arm (green, truth)")
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog="earcore run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, help="TOML file (see `earcore config dump`); missing keys keep defaults")
    parser.add_argument("--duration", type=seconds, help="simulated seconds (default 30)")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (default ./out)")
    parser.add_argument("--seed", type=count, help="random seed of the cell (noise, random reaches)")
    parser.add_argument("--camera-scale", type=scale, help="render every camera at this fraction of its resolution")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--no-recording", action="store_true", help="skip the rerun recording (out/cell.rrd)")
    args = parser.parse_args(argv)
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"argument --out: {args.out} is a file; give a folder for the outputs")
    config = load_config(args.config) if args.config else RunConfig()
    if args.duration is not None:
        config.duration = args.duration
        config.snapshots = [t for t in config.snapshots if t < args.duration] or [args.duration * 0.99]
    if args.seed is not None:
        config.cell.seed = args.seed
    if args.camera_scale is not None:
        config.cell.camera_scale = args.camera_scale
    record = not args.no_recording
    if record:
        try:
            import rerun  # noqa: F401
        except ImportError:
            print("earcore run: rerun-sdk is not installed, skipping the recording (pip install 'earcore[viz]')", file=sys.stderr)
            record = False
    summary = run(config, args.out, progress=not args.quiet, record=record)
    print(
        f"{summary['frames']} frames, {summary['simulated_s']:.1f} s simulated in {summary['wall_s']:.0f} s; "
        f"perception {summary['perception_ms_total_mean']:.1f} ms/frame; "
        f"{summary['robot_points_leak_fraction']:.2%} of robot points reached the map; "
        f"arm in map in {summary['frames_arm_in_map']}/{summary['frames_arm_seen']} frames where seen; "
        f"{summary['danger_voxels']} dangerous voxels -> {args.out}/summary.json"
    )
    return 0


def config_main(argv: list[str]) -> int:
    if argv in (["--help"], ["-h"], ["dump", "--help"], ["dump", "-h"]):
        print("usage: earcore config dump   (prints every option of `earcore run` with its default, as TOML)")
        return 0
    if argv == ["dump"]:
        sys.stdout.write(dump_toml(RunConfig()))
        return 0
    return fail("earcore config", "the only command is `earcore config dump` (every option with its default, as TOML)")
