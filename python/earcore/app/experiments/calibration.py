"""Paper I's Tables II-III in the simulated cell: how the calibration's accuracy depends
on the frames used, tilting, overlap and field-of-view coverage.

One full run of Algorithm 1 per camera (the dense trajectory, `full_trajectory`) (three cameras: two Kinect V2-like, one Kinect
V1-like, each moved 5 cm / 5° off its nominal place) collects every frame; each row
then re-solves steps 6-7 (lenses, offset, eye-to-hand) from a subset of those frames
and compares the result with the simulation's truth:

  overlap   every position of each stage's ring (neighbouring boards overlap in the
            image) or every other one (they do not);
  tilting   the tilted frames kept (yes) or only the board facing the camera (no);
  field     the whole staged trajectory (full) or its inner stages (centre);
  frames    N frames spread evenly over the trajectory (a sparser trajectory over the
            same field of view; the start and tilt-limit frames always count);
  depth     the depth error fitted and taken out (step 7's depth distortion) or not.

    earcore experiment calibration [--seed 0] [--out out/calibration]
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from earcore import jsonfile
from earcore.app.calibration_cell import calibration_cell, calibration_cell_config, evaluate
from earcore.calibration.config import CalibrationConfig, full_trajectory
from earcore.calibration.errors import CalibrationError
from earcore.calibration.estimate import Observation
from earcore.calibration.procedure import Calibrator

__all__ = ["ROWS", "Row", "calibration_table", "format_table", "select"]


@dataclass(frozen=True)
class Row:
    label: str
    overlap: bool = True
    tilting: bool = True
    field: str = "full"
    frames: int | None = None
    depth_correction: bool = True


#: The table's rows, from everything down to a handful of frames.
ROWS = [
    Row("all frames"),
    Row("no overlap", overlap=False),
    Row("no overlap, 20 frames", overlap=False, frames=20),
    Row("30 frames", frames=30),
    Row("20 frames", frames=20),
    Row("15 frames", frames=15),
    Row("no tilting", tilting=False),
    Row("centre only", field="centre"),
    Row("centre only, no tilting", tilting=False, field="centre"),
    Row("10 frames", frames=10),
    Row("no depth correction", depth_correction=False),
]


def select(observations: list[Observation], row: Row) -> list[Observation]:
    """The frames a row re-solves from (start and tilt-limit frames are always kept:
    without them there is no mount; `tilting=False` drops the tilted stage frames)."""
    fixed, stage = [], []
    for o in observations:
        if o.phase != "stage":
            fixed.append(o)
            continue
        if not row.overlap and o.slot is not None and o.slot % 2 == 1:
            continue
        if not row.tilting and o.tilted:
            continue
        if row.field == "centre" and o.radius is not None and o.radius > 0.5:
            continue
        stage.append(o)
    if row.frames is not None and len(fixed) + len(stage) > row.frames:
        keep = max(row.frames - len(fixed), 0)
        picks = np.unique(np.round(np.linspace(0, len(stage) - 1, keep)).astype(int)) if keep else np.zeros(0, int)
        stage = [stage[int(i)] for i in picks]
    return (fixed + stage)[: row.frames] if row.frames else fixed + stage


def calibration_table(seed: int = 0, camera_scale: float = 1.0, out: Path | None = None, progress=print) -> dict:
    """Run the experiment; returns {"rows": [...], "run": {...}}."""
    config = calibration_cell_config(seed, camera_scale)
    cell, mount = calibration_cell(config, seed=seed)
    # The experiment reports every camera's errors, however uncertain: no quality limit.
    settings = full_trajectory(CalibrationConfig(seed=seed, max_pose_sigma_m=None, max_pose_sigma_deg=None))
    calibrator = Calibrator(cell, settings, progress=progress)
    started = time.perf_counter()
    full = calibrator.run()
    run = {
        "motion_s": calibrator.motion_time,
        "solver_s": calibrator.solver_time,
        "wall_s": time.perf_counter() - started,
        "frames": {name: cal.frames for name, cal in full.items()},
    }
    rows = []
    terms = calibrator.config.depth_error_terms
    for row in ROWS:
        entry = {"row": asdict(row), "cameras": {}}
        for name in full:
            subset = select(calibrator.observations[name], row)
            calibrator.config.depth_error_terms = terms if row.depth_correction else ()
            try:
                cal = calibrator.finish(name, subset)
            except CalibrationError as exc:
                entry["cameras"][name] = {"frames": len(subset), "error": str(exc)}
                continue
            err = evaluate(cell, cal, mount, subset)
            entry["cameras"][name] = {
                "frames": len(subset),
                "x_mm": 1000 * abs(err.translation_xyz[0]),
                "y_mm": 1000 * abs(err.translation_xyz[1]),
                "z_mm": 1000 * abs(err.translation_xyz[2]),
                "translation_mm": 1000 * err.translation,
                "rotation_deg": err.rotation_deg,
                "reprojection_px": cal.depth_reprojection_rms,
                "zhang_px": cal.zhang_reprojection_rms,
                "lens_px": err.depth_lens_px,
                "depth_mm": 1000 * err.depth_error_rms,
            }
        rows.append(entry)
    calibrator.config.depth_error_terms = terms
    cell.close()
    result = {"rows": rows, "run": run, "seed": seed}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "calibration_table.json").write_text(jsonfile.dumps(result, indent=2))
    return result


def format_table(result: dict) -> str:
    names = list(result["run"]["frames"])
    short = {n: n.replace("kinect_", "").replace("_", " ") for n in names}
    head = (f"{'experiment':<26} {'overlap':>7} {'tilt':>4} {'field':>6} | "
            + " ".join(f"{'frames ' + short[n]:>15}" for n in names)
            + f" | {'x mm':>5} {'y mm':>5} {'z mm':>5} {'rot °':>6} {'repr px':>7} {'lens px':>7} {'depth mm':>8}")
    lines = [head, "-" * len(head)]
    for entry in result["rows"]:
        row = entry["row"]
        cams = entry["cameras"]
        ok = [c for c in cams.values() if "error" not in c]

        def mean(key):
            return float(np.mean([c[key] for c in ok])) if ok else float("nan")

        frames = " ".join(f"{cams[n]['frames']:>15}" for n in names)
        lines.append(
            f"{row['label']:<26} {'yes' if row['overlap'] else 'no':>7} {'yes' if row['tilting'] else 'no':>4} {row['field']:>6} | "
            f"{frames} | {mean('x_mm'):5.2f} {mean('y_mm'):5.2f} {mean('z_mm'):5.2f} {mean('rotation_deg'):6.3f} "
            f"{mean('reprojection_px'):7.3f} {mean('lens_px'):7.2f} {mean('depth_mm'):8.2f}"
            + ("" if len(ok) == len(cams) else f"  ({len(cams) - len(ok)} failed)")
        )
    run = result["run"]
    lines.append(
        f"full run: {run['motion_s']:.0f} s of robot motion for {len(names)} cameras, {run['solver_s']:.1f} s in the "
        f"solvers, {run['wall_s']:.0f} s wall; errors are means over the cameras (x, y along the image, z along the view)"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from earcore.app.arguments import Parser, count, scale

    parser = Parser(prog="earcore experiment calibration", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=count, default=0)
    parser.add_argument("--camera-scale", type=scale, default=1.0, help="camera resolution factor")
    parser.add_argument("--out", type=Path, default=Path("out/calibration"))
    args = parser.parse_args(argv)
    if args.camera_scale < 0.25:
        parser.error(f"argument --camera-scale: the board's corners are not found below 0.25, got {args.camera_scale:g}")
    result = calibration_table(args.seed, args.camera_scale, args.out,
                               progress=lambda m: print(f"[{time.strftime('%H:%M:%S')}] {m}", flush=True))
    print(format_table(result))
    print(f"figures: {args.out / 'calibration_table.json'}")
    return 0
