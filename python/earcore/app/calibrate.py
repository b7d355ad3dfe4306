"""`earcore calibrate`: Paper I's automatic calibration in the simulated cell.

    earcore calibrate [--out calibration.yaml] [--camera NAME ...] [--seed 0] [--full]
                      [--max-pose-sigma MM DEG | --accept-uncertain]
    earcore calibrate --check [--bump NAME]        # has a camera moved?
    earcore calibrate --camera NAME [--bump NAME]  # recalibrate only that camera

Every fixed camera is calibrated unless `--camera` names some; the file gets the named
cameras merged in (the others keep their entries), and is only written when every named
camera succeeded: a camera whose pose is less certain than `--max-pose-sigma` (1σ,
default 5 mm / 0.5°) counts as failed. `--bump NAME` moves that camera 10 cm / 10° in the simulation first
(someone knocked it) to try the check and the recalibration.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from earcore.app.arguments import Parser, count, fail, positive, scale

__all__ = ["main"]


def _say(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def main(argv: list[str] | None = None) -> int:
    from earcore.app.calibration_cell import calibration_cell, calibration_cell_config, evaluate
    from earcore.calibration.check import check_camera
    from earcore.calibration.config import CalibrationConfig, full_trajectory
    from earcore.calibration.errors import CalibrationError, CalibrationFileError
    from earcore.calibration.procedure import Calibrator
    from earcore.calibration.store import Calibration
    from earcore.transforms import perturb_pose

    parser = Parser(prog="earcore calibrate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("calibration.yaml"), help="the calibration file (default calibration.yaml)")
    parser.add_argument("--camera", nargs="*", default=None, help="calibrate (or check) only these cameras")
    parser.add_argument("--check", action="store_true", help="only check the cameras in --out against the board")
    parser.add_argument("--bump", nargs="*", default=[], help="simulation: move these cameras 10 cm / 10° first")
    parser.add_argument("--seed", type=count, default=0)
    parser.add_argument("--camera-scale", type=scale, default=1.0, help="camera resolution factor (1 = the sensors' own)")
    parser.add_argument("--max-frames", type=lambda text: count(text, 8), default=20,
                        help="frames per camera (default 20: three cameras in under 3 minutes of motion; Paper I: ~30)")
    parser.add_argument("--full", action="store_true", help="the whole trajectory (both distances, every position)")
    parser.add_argument("--no-tilt", action="store_true", help="no tilting along the trajectory")
    quality = parser.add_mutually_exclusive_group()
    quality.add_argument("--max-pose-sigma", nargs=2, type=positive, metavar=("MM", "DEG"), default=(5.0, 0.5),
                         help="refuse (exit 1, file unchanged) a camera whose pose is less certain than this, 1σ (default 5 mm 0.5°)")
    quality.add_argument("--accept-uncertain", action="store_true", help="write every camera whatever its pose's uncertainty")
    args = parser.parse_args(argv)
    if args.camera_scale < 0.25:
        parser.error(f"argument --camera-scale: the board's corners are not found below 0.25, got {args.camera_scale:g}")

    cell, true_mount = calibration_cell(calibration_cell_config(args.seed, args.camera_scale), seed=args.seed)
    bump_rng = np.random.default_rng([args.seed, 99])
    for name in args.bump:
        cam = next((c for c in cell.cameras if c.name == name), None)
        if cam is None:
            return fail("earcore calibrate", f"argument --bump: no camera {name!r}; cameras: {[c.name for c in cell.cameras]}")
        cam.place(perturb_pose(cam.base_from_camera, 0.10, np.radians(10.0), bump_rng))
        _say(f"simulation: {name} bumped by 10 cm / 10°")
    limit_mm, limit_deg = (None, None) if args.accept_uncertain else args.max_pose_sigma
    settings = CalibrationConfig(
        max_frames=args.max_frames, tilt_fraction=0.0 if args.no_tilt else 0.7, seed=args.seed,
        max_pose_sigma_m=None if limit_mm is None else limit_mm / 1000, max_pose_sigma_deg=limit_deg,
    )
    if args.full:
        settings = full_trajectory(settings)
    calibrator = Calibrator(cell, settings, progress=_say)
    fixed = [c.name for c in cell.cameras if c.mount is None]
    names = args.camera or fixed
    unknown = sorted(set(names) - set(fixed))
    if unknown:
        return fail("earcore calibrate", f"argument --camera: unknown cameras {unknown}; fixed cameras: {fixed}")

    if args.check:
        try:
            existing = Calibration.load(args.out)
        except CalibrationFileError as exc:
            return fail("earcore calibrate", str(exc))
        moved = []
        for name in names:
            if name not in existing.cameras:
                _say(f"{name}: not in {args.out}")
                moved.append(name)
                continue
            try:
                result = check_camera(calibrator, existing.cameras[name])
            except CalibrationFileError as exc:  # made for images of another size: not comparable
                _say(f"{name}: not checked: {exc}")
                moved.append(name)
                continue
            _say(str(result))
            if result.moved:
                moved.append(name)
        if moved:
            bump = f" --bump {' '.join(args.bump)}" if args.bump else ""  # the simulation is rebuilt each run
            _say(f"recalibrate with: earcore calibrate --out {args.out} --camera {' '.join(moved)}{bump}")
        return 1 if moved else 0

    started = time.perf_counter()
    try:
        results = calibrator.run_to_file(args.out, names)
    except CalibrationError as exc:
        return fail("earcore calibrate", f"{exc}; {args.out} left unchanged", 1)
    _say(f"wrote {args.out}: {', '.join(results)} ({calibrator.motion_time:.0f} s of robot motion, "
         f"{calibrator.solver_time:.1f} s in the solvers, {time.perf_counter() - started:.0f} s wall)")
    for name, cal in results.items():
        err = evaluate(cell, cal, true_mount, calibrator.observations[name])
        ex, ey, ez = (1000 * v for v in err.translation_xyz)
        rms, lens = (cal.depth_reprojection_rms, err.depth_lens_px) if cal.has_depth else (cal.colour_reprojection_rms, err.colour_lens_px)
        line = (f"  {name}: {cal.frames} frames, lens {rms:.2f} px rms; against the simulation's truth: "
                f"{1000 * err.translation:.1f} mm (x {ex:+.1f}, y {ey:+.1f}, z {ez:+.1f}), {err.rotation_deg:.2f}°, "
                f"lens within {lens:.2f} px where seen")
        if cal.has_depth:
            line += (f", depth error left {1000 * err.depth_error_rms:.1f} mm rms, colour-depth offset "
                     f"{1000 * err.offset_translation:.1f} mm / {err.offset_rotation_deg:.2f}°; "
                     f"pose ±{1000 * cal.pose_sigma_m:.1f} mm / ±{cal.pose_sigma_deg:.2f}° (1σ: from pixels "
                     f"±{1000 * cal.pixel_pose_sigma_m:.1f} mm, {1000 * cal.pose_agreement_m:.1f} mm from the pose from depth)")
        else:
            line += f" (colour only: AX = ZB); pose ±{1000 * cal.pose_sigma_m:.1f} mm / ±{cal.pose_sigma_deg:.2f}° (1σ)"
        _say(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
