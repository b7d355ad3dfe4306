"""`earcore charge`: Paper III's charging station in simulation, over many parkings.

    earcore charge --runs 20                     # Type 2 port and plug, parkings at 0-45°
    earcore charge --runs 5 --port type1         # a car the plug does not fit: refused

Each run parks the car at random (within a 20 x 20 cm area, the port 0-`--max-angle`°
to the cameras), finds the port in both images, plans the three steps and plugs in with
the force watched, pauses, unplugs and returns to stand-by, or refuses before moving.
Per run, `run-NN.png` shows both images around the port (found pins red, true pins
green), the force along the plug's axis and the numbers; `summary.json` and
`summary.png` gather the runs.

Before the first car, the station calibrates itself without markers
(`--camera-pose markerless`, the default; `app.charge_calibration`): the left camera in
the robot's base and the plug's tip on the flange, from the plug's pins in up to
`--calibration-poses` poses the robot picks. It starts from the installation's rough
values (the simulation's truth `--rough MM,DEG` off) and reports its error against the
truth. `--camera-pose truth` skips it and uses the simulation's truth.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from earcore import jsonfile
from earcore.app.arguments import Parser, count, fail, positive_int, scale

__all__ = ["main"]

#: Plugged in, as the simulation's truth sees it: the plug's tip within this of the
#: mated pose along the axis (m).
MATED_TOLERANCE = 0.001


def _parser(prog: str) -> Parser:
    parser = Parser(prog=prog, description="The charging station (Paper III): find the port, plug in and out (docs/charging.md).")
    parser.add_argument("--runs", type=positive_int, default=20, help="parkings to try (default 20)")
    parser.add_argument("--seed", type=count, default=0, help="the parkings' random seed (default 0)")
    parser.add_argument("--port", default="type2", help="the car's port: type2 or type1 (default type2)")
    parser.add_argument("--plug", default="type2", help="the robot's plug: type2 or type1 (default type2)")
    parser.add_argument("--max-angle", type=float, default=45.0, help="the port's largest angle to the cameras (degrees, default 45)")
    parser.add_argument("--camera-scale", type=scale, default=1.0, help="the cameras' resolution as a fraction of 2448x2048 (default 1)")
    parser.add_argument("--force-threshold", type=float, default=25.0, help="stop inserting above this force along the axis (N, default 25)")
    parser.add_argument("--camera-pose", choices=("markerless", "truth"), default="markerless", help="calibrate without markers first (default) or use the truth")
    parser.add_argument("--calibration-poses", type=positive_int, default=30, help="poses the robot may use to calibrate (default 30)")
    parser.add_argument("--rough", type=_rough, default=(30.0, 3.0), metavar="MM,DEG", help="how far off the installation's rough camera pose is (default 30,3)")
    parser.add_argument("--out", type=Path, default=Path("out/charge"), help="where the reports go (default out/charge)")
    return parser


def _rough(text: str) -> tuple[float, float]:
    """MM,DEG: two finite numbers >= 0."""
    import argparse
    import math

    try:
        mm, deg = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MM,DEG, got {text!r}") from None
    if not (math.isfinite(mm) and math.isfinite(deg) and mm >= 0 and deg >= 0):
        raise argparse.ArgumentTypeError(f"MM and DEG must be finite and >= 0, got {text!r}")
    return mm, deg


def _pose_errors(estimate: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    from earcore.transforms import rotation_vector

    local = np.linalg.inv(truth) @ estimate
    return {
        "position_mm": float(np.linalg.norm(local[:3, 3]) * 1000),
        "rotation_deg": float(np.degrees(np.linalg.norm(rotation_vector(local[:3, :3])))),
        "about_axis_deg": float(np.degrees(abs(np.arctan2(local[1, 0], local[0, 0])))),
    }


def _record(cell, outcome, seconds: float, plugged_truth: bool | None) -> dict[str, Any]:
    rec: dict[str, Any] = {
        "status": outcome.status,
        "reason": outcome.reason,
        "port_type_seen": outcome.port_type,
        "parking": {
            "angle_deg": cell.parking.angle_deg,
            "roll_deg": cell.parking.roll_deg,
            "distance_m": float(np.linalg.norm(cell.base_from_port[:3, 3] - cell.cameras[0].base_from_camera[:3, 3])),
        },
        "seconds": seconds,
    }
    if outcome.base_from_port is not None:
        rec["pose_error"] = _pose_errors(outcome.base_from_port, cell.base_from_port)
    if outcome.estimate is not None:
        rec["match_scores"] = [m.score for m in outcome.estimate.matches]
        rec["pins_fit_mm"] = outcome.estimate.fit_mm
    if outcome.result is not None:
        r = outcome.result
        rec.update(inserted=r.inserted, plugged_truth=plugged_truth, depth_mm=r.depth * 1000, peak_force_n=r.peak_force, motion_seconds=r.seconds)
        if outcome.unplug_trace is not None and len(outcome.unplug_trace):
            rec["unplug_peak_pull_n"] = float(-outcome.unplug_trace[:, 1].min())
    return rec


def _crop(image: np.ndarray, pixels: np.ndarray, margin: int = 60) -> tuple[np.ndarray, np.ndarray]:
    h, w = image.shape[:2]
    x0, y0 = np.maximum(np.floor(pixels.min(0)).astype(int) - margin, 0)
    x1, y1 = np.minimum(np.ceil(pixels.max(0)).astype(int) + margin, [w, h])
    return image[y0:y1, x0:x1], np.array([x0, y0])


def _report(path: Path, cell, outcome, rec: dict[str, Any], threshold: float, limit: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from earcore.charging.stereo import project_points

    k = cell.port_connector
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for ax, image, camera in zip(axes[:2], outcome.images, cell.cameras):
        truth_cam = np.linalg.inv(camera.base_from_camera) @ cell.base_from_port
        sensor = camera.sensor
        dist = np.asarray(sensor.distortion, dtype=np.float64)
        true_px = project_points(k.reference_points @ truth_cam[:3, :3].T + truth_cam[:3, 3], sensor.intrinsics, dist)
        crop, origin = _crop(image, true_px)
        ax.imshow(crop)
        ax.plot(*(true_px - origin).T, "o", mfc="none", mec="lime", ms=9, label="true pins")
        if outcome.base_from_port is not None:
            est_cam = np.linalg.inv(camera.base_from_camera) @ outcome.base_from_port
            est_px = project_points(k.reference_points @ est_cam[:3, :3].T + est_cam[:3, 3], sensor.intrinsics, dist)
            ax.plot(*(est_px - origin).T, "+", color="red", ms=9, label="found pins")
        ax.set_title(f"{camera.name} camera")
        ax.axis("off")
    axes[0].legend(loc="lower left", fontsize=8)
    ax = axes[2]
    r = outcome.result
    if r is not None and len(r.trace):
        t0 = r.trace[0, 0]
        ax.plot(r.trace[:, 0] - t0, r.trace[:, 1], label="align + insert")
        if outcome.unplug_trace is not None and len(outcome.unplug_trace):
            ax.plot(outcome.unplug_trace[:, 0] - t0, outcome.unplug_trace[:, 1], label="pause + unplug")
        ax.axhline(threshold, color="orange", ls="--", lw=1, label=f"stop {threshold:.0f} N")
        ax.axhline(limit, color="red", ls=":", lw=1, label=f"pin limit {limit:.0f} N")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("force along the plug's axis (N)")
        ax.legend(fontsize=8)
    else:
        ax.axis("off")
    lines = [f"{rec['status'].upper()}" + (f": {rec['reason']}" if rec["reason"] else "")]
    if "pose_error" in rec:
        e = rec["pose_error"]
        lines.append(f"port pose error {e['position_mm']:.2f} mm, {e['rotation_deg']:.2f}° ({e['about_axis_deg']:.2f}° about the axis)")
    p = rec["parking"]
    lines.append(f"parking: {p['angle_deg']:.0f}° to the cameras, {p['distance_m']:.2f} m away")
    fig.suptitle("\n".join(_wrap(line) for line in lines), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _wrap(text: str, width: int = 150) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def _summary_figure(path: Path, runs: list[dict[str, Any]], threshold: float, limit: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    statuses = ["plugged", "blocked", "not reached", "stuck", "refused"]
    colours = ["tab:green", "tab:orange", "tab:purple", "tab:red", "tab:gray"]
    axes[0].bar(statuses, [sum(r["status"] == s for r in runs) for s in statuses], color=colours)
    axes[0].set_title(f"{len(runs)} parkings")
    errors = [r["pose_error"] for r in runs if "pose_error" in r]
    if errors:
        dots = axes[1].scatter(
            [e["position_mm"] for e in errors], [e["rotation_deg"] for e in errors], c=[r["parking"]["angle_deg"] for r in runs if "pose_error" in r], cmap="viridis"
        )
        fig.colorbar(dots, ax=axes[1], label="port's angle to the cameras (°)")
        axes[1].set_xlabel("position error (mm)")
        axes[1].set_ylabel("rotation error (°)")
        axes[1].set_title("port pose against the truth")
    peaks = [r["peak_force_n"] for r in runs if "peak_force_n" in r]
    if peaks:
        axes[2].hist(peaks, bins=10, color="tab:blue")
        axes[2].axvline(threshold, color="orange", ls="--", label="stop")
        axes[2].axvline(limit, color="red", ls=":", label="pin limit")
        axes[2].set_xlabel("peak force while inserting (N)")
        axes[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    prog = "earcore charge"
    args = _parser(prog).parse_args(argv)
    from earcore import robots
    from earcore.charging.plug_in import PlugInConfig
    from earcore.charging.session import charge
    from earcore.errors import ConfigError, EarcoreError
    from earcore.sim.charging_cell import STANDBY, ChargingCell, ChargingCellConfig

    try:
        cfg = ChargingCellConfig(seed=args.seed, port=args.port, plug=args.plug, max_angle_deg=args.max_angle, camera_scale=args.camera_scale)
        plug_config = PlugInConfig(force_threshold=args.force_threshold)
        cell = ChargingCell(cfg)
    except (ConfigError, ValueError) as exc:
        return fail(prog, str(exc))
    args.out.mkdir(parents=True, exist_ok=True)
    robot = robots.load(cfg.robot)
    link = robot.link_names.index(robots.FLANGES[cfg.robot][0])
    runs = []
    try:
        try:
            base_from_camera, flange_from_tip, calibration = _calibrate(cell, robot, link, args)
        except (EarcoreError, ValueError) as exc:
            return fail(prog, f"calibration: {exc}", 1)
        for i in range(args.runs):
            if i:
                cell.park()
            cell.set_joints(STANDBY)
            start = time.perf_counter()
            outcome = charge(
                cell,
                robot,
                link,
                base_from_camera,
                plug=args.plug,
                standby=STANDBY,
                config=plug_config,
                flange_from_tip=flange_from_tip,
                judge=lambda: _mated(cell),
            )
            seconds = time.perf_counter() - start
            rec = _record(cell, outcome, seconds, outcome.judged)
            runs.append(rec)
            _report(args.out / f"run-{i:02d}.png", cell, outcome, rec, plug_config.force_threshold, plug_config.force_limit)
            print(
                f"run {i:2d}: {rec['status']:8s} {rec['reason'][:90]}"
                + (f"  pose {rec['pose_error']['position_mm']:.2f} mm {rec['pose_error']['rotation_deg']:.2f}°" if "pose_error" in rec else "")
                + (f"  NOT MATED in the simulation ({rec['depth_mm']:.1f} mm in)"
                   if rec["status"] == "plugged" and rec.get("plugged_truth") is False else ""),
                flush=True,
            )
    finally:
        cell.close()
    plugged = [r for r in runs if r["status"] == "plugged"]
    summary = {
        "runs": len(runs),
        "plugged": len(plugged),
        "plugged_truth": sum(bool(r.get("plugged_truth")) for r in runs),
        "blocked": sum(r["status"] == "blocked" for r in runs),
        "not_reached": sum(r["status"] == "not reached" for r in runs),
        "stuck": sum(r["status"] == "stuck" for r in runs),
        "refused": sum(r["status"] == "refused" for r in runs),
        "attempted_while_flagged": 0,  # a flagged estimate is refused before planning (charging.session)
        "max_peak_force_n": max((r["peak_force_n"] for r in runs if "peak_force_n" in r), default=0.0),
        "force_limit_n": plug_config.force_limit,
        "median_position_mm": _median([r["pose_error"]["position_mm"] for r in runs if "pose_error" in r]),
        "median_rotation_deg": _median([r["pose_error"]["rotation_deg"] for r in runs if "pose_error" in r]),
        "max_about_axis_deg": max((r["pose_error"]["about_axis_deg"] for r in runs if "pose_error" in r), default=float("nan")),
        "calibration": calibration,
        "config": {"seed": args.seed, "port": args.port, "plug": args.plug, "max_angle_deg": args.max_angle, "camera_scale": args.camera_scale},
        "per_run": runs,
    }
    (args.out / "summary.json").write_text(jsonfile.dumps(summary, indent=1))
    _summary_figure(args.out / "summary.png", runs, plug_config.force_threshold, plug_config.force_limit)
    posed = any("pose_error" in r for r in runs)
    pose = f"port pose {summary['median_position_mm']:.2f} mm / {summary['median_rotation_deg']:.2f}° median" if posed else "no port pose estimated"
    print(
        f"{summary['plugged']}/{len(runs)} plugged in ({summary['plugged_truth']} confirmed by the simulation), {summary['blocked']} blocked, "
        f"{summary['not_reached']} not reached, {summary['stuck']} stuck, {summary['refused']} refused; peak force {summary['max_peak_force_n']:.1f} N "
        f"(limit {plug_config.force_limit:.0f} N); {pose} -> {args.out}"
    )
    return 0


def _calibrate(cell, robot, link, args) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The left camera's pose and the plug's tip on the flange: calibrated without
    markers with the car away (and their errors against the truth), or the truth."""
    from earcore.app.charge_calibration import MarkerlessConfig, calibrate_markerless, workspace_error_mm
    from earcore.transforms import pose_from_vector, rotation_angle

    true_camera, true_tip = cell.cameras[0].base_from_camera, cell.flange_from_tip
    if args.camera_pose == "truth":
        return true_camera, true_tip, {"method": "truth (simulation)"}
    mm, deg = args.rough
    rng = np.random.default_rng([args.seed, 7])

    def off(translation: float, rotation_deg: float) -> np.ndarray:
        t, r = rng.normal(size=3), rng.normal(size=3)
        return pose_from_vector(np.r_[t / np.linalg.norm(t) * translation, r / np.linalg.norm(r) * np.radians(rotation_deg)])

    rough_camera = true_camera @ off(mm / 1000, deg)
    rough_tip = true_tip @ off(0.005, 2.0)  # the holder as designed, not as built
    cell.drive_away()
    print(f"calibrating without markers: up to {args.calibration_poses} plug poses ...", flush=True)
    start = time.perf_counter()
    result = calibrate_markerless(cell, robot, link, cell.plug_connector, rough_camera, rough_tip, MarkerlessConfig(poses=args.calibration_poses, seed=args.seed))
    cell.park()
    workspace = workspace_error_mm(result.base_from_camera, true_camera, np.asarray(cell.config.port_nominal))
    tip_mm = float(np.linalg.norm(result.flange_from_tip[:3, 3] - true_tip[:3, 3]) * 1000)
    report = {
        "method": "markerless (Tsai-Lenz, then a joint fit)",
        "poses_tried": result.tried,
        "poses_used": result.used,
        "rmse_mm": result.rmse_mm,
        "camera_workspace_error_mm": workspace,
        "camera_translation_error_mm": float(np.linalg.norm(result.base_from_camera[:3, 3] - true_camera[:3, 3]) * 1000),
        "camera_rotation_error_deg": float(np.degrees(rotation_angle(result.base_from_camera, true_camera))),
        "tip_translation_error_mm": tip_mm,
        "tip_rotation_error_deg": float(np.degrees(rotation_angle(result.flange_from_tip, true_tip))),
        "tsai_camera_workspace_error_mm": workspace_error_mm(result.tsai[0], true_camera, np.asarray(cell.config.port_nominal)),
        "seconds": time.perf_counter() - start,
        "discarded": result.discarded,
    }
    print(
        f"calibrated from {result.used} of {result.tried} poses: camera {workspace:.2f} mm off over the workspace, plug tip {tip_mm:.2f} mm off "
        f"(Tsai-Lenz alone: {report['tsai_camera_workspace_error_mm']:.1f} mm)",
        flush=True,
    )
    return result.base_from_camera, result.flange_from_tip, report


def _mated(cell) -> bool:
    """The simulation's truth: the plug's tip at the port's face, on its axis."""
    local = np.linalg.inv(cell.base_from_port) @ cell.base_from_plug()
    return bool(abs(local[2, 3]) < MATED_TOLERANCE and np.linalg.norm(local[:2, 3]) < cell.plug_connector.clearance * 2)


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")
