"""`earcore parts show`: "show me this part". In the simulated cell's parts station, find
a part in the camera's current image, give its pickup points in the robot's base frame
and mark them in a picture (and a rerun recording).

    earcore parts show --model runs/parts --part Motor               # a type the detector knows
    earcore parts show --model runs/oneshot --needle-part Axis       # one image of a new part
    earcore parts show --model runs/oneshot --needle axis.png --needle-mask axis-mask.png --needle-depth axis-depth.png

With a one-shot segmenter the part is given by one image of it (the needle): rendered
alone on the platform (`--needle-part`) or your own colour image and the part's mask
(`--needle`, `--needle-mask`: PNGs, the mask non-zero on the part; `--needle-depth`, a
16-bit PNG in mm, for an RGB-D segmenter), taken at the camera's scale (`--size`). The picture
(out/show.png, 4x the camera's size) tints what the network segments, circles each
pickup point (red) and crosses the parts' true centres (green); the needle's crop sits
in the top left corner. Each pick's error to the nearest true part of the type is reported:
the station knows the truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from earcore import jsonfile
from earcore.app.arguments import Parser, count, fail, positive_int

__all__ = ["main"]

SCALE = 4


def _parser(prog: str) -> Parser:
    parser = Parser(prog=prog, description="Find a part in the parts station's camera image and pick it (docs/parts.md).")
    parser.add_argument("--model", type=Path, required=True, help="a trained parts detector or one-shot segmenter (run folder or checkpoint)")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--part", help="the part type to find (a detector's type)")
    which.add_argument("--needle-part", help="render one image of this part type as the needle (one-shot)")
    which.add_argument("--needle", type=Path, help="the needle: a colour PNG of the part, at the camera's scale (one-shot; with --needle-mask)")
    parser.add_argument("--needle-mask", type=Path, help="the needle's part pixels: a PNG, non-zero on the part")
    parser.add_argument("--needle-depth", type=Path, help="the needle's depth: a 16-bit PNG in mm (an RGB-D segmenter needs it)")
    parser.add_argument(
        "--size", type=_size, default=(128, 96), help="the camera image WIDTHxHEIGHT for a one-shot segmenter (default 128x96; a detector's is its own)"
    )
    parser.add_argument("--seed", type=count, default=0, help="the station's scenes (default 0)")
    parser.add_argument("--view", type=count, default=None, help="which view of the station (default: the first that shows the part)")
    parser.add_argument("--calibration-error", default="1.5,0.06", metavar="MM,DEG", help="the camera pose's error, as a calibration leaves it (default 1.5,0.06)")
    parser.add_argument("--min-pixels", type=positive_int, default=12, help="smallest region taken for a part (default 12 px)")
    parser.add_argument("--out", type=Path, default=Path("out/parts-show"), help="where show.png and show.json go")
    parser.add_argument("--recording", type=Path, default=None, help="also write a rerun recording (.rrd) of the image, the segmentation and the picks")
    return parser


def _size(text: str) -> tuple[int, int]:
    from earcore.app.dataset import _size as size

    return size(text)


def _load_model(path: Path):
    """(kind, model, meta): a parts detector or a one-shot segmenter, by the checkpoint."""
    from earcore.learning.checkpoint import load_checkpoint
    from earcore.parts.oneshot_train import NETWORK as ONESHOT
    from earcore.parts.oneshot_train import load_oneshot
    from earcore.parts.train import NETWORK as DETECTOR
    from earcore.parts.train import load_detector

    network = load_checkpoint(path).meta.get("network")
    if network == DETECTOR:
        return ("detector", *load_detector(path))
    if network == ONESHOT:
        return ("oneshot", *load_oneshot(path))
    from earcore.errors import ConfigError

    raise ConfigError(f"{path}: holds a {network!r} network, not a parts detector or one-shot segmenter")


def _first_view(station, view: int | None, cls: int | None, tries: int = 100):
    """(index, view): `view` if given, else the first of the station's views showing
    class `cls` (view 0 when none of the first `tries` does or the class is unknown)."""
    if view is not None or cls is None:
        return view or 0, station.view(view or 0)
    for index in range(tries):
        candidate = station.view(index)
        if (candidate.classes == cls).any():
            return index, candidate
    return 0, station.view(0)


def _png(path: Path, what: str, channels: int | None) -> np.ndarray:
    """A PNG as (H, W, channels) uint8 (colour) or (H, W) uint16 / bool sources."""
    from earcore.learning import png

    image = png.read(path)
    if channels is None:
        return image if image.ndim == 2 else image[..., 0]
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise ValueError(f"{path}: the {what} must be an 8- or 16-bit PNG, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(image[..., :channels])


def _needle(args, classes: list[str], size: tuple[int, int], seed: int, divisor: int):
    from earcore.parts.find import Needle
    from earcore.sim.part_station import PartStation

    if args.needle_part is not None:
        if args.needle_part not in classes:
            raise ValueError(f"unknown part type {args.needle_part!r}; known: {', '.join(classes)}")
        with PartStation(width=size[0], height=size[1], seed=seed + 1, objects=(1, 1), classes=(args.needle_part,)) as alone:
            view = alone.view(0)
        return Needle.from_image(view.rgb, view.depth_mm, view.instances == 1, divisor=divisor)
    if args.needle_mask is None:
        raise ValueError("--needle needs --needle-mask (the part's pixels)")
    rgb = _png(args.needle, "needle", 3)
    mask = _png(args.needle_mask, "needle mask", None) > 0
    depth = None if args.needle_depth is None else _png(args.needle_depth, "needle depth", None).astype(np.uint16)
    return Needle.from_image(rgb, depth, mask, camera_width=size[0], divisor=divisor)


def _picture(view, belief: np.ndarray, picks, truth_pixels: np.ndarray, needle_rgb: np.ndarray | None) -> np.ndarray:
    from earcore.pose.overlay import overlay

    big = np.repeat(np.repeat(view.rgb, SCALE, axis=0), SCALE, axis=1)
    mask = np.repeat(np.repeat(belief > 0.5, SCALE, axis=0), SCALE, axis=1)
    scaled = [((u + 0.5) * SCALE - 0.5, (v + 0.5) * SCALE - 0.5) for u, v in (p.pixel for p, _ in picks)]
    out = overlay(big, mask=mask, predicted=np.array(scaled).reshape(-1, 2), truth=(truth_pixels + 0.5) * SCALE - 0.5, radius=2.5 * SCALE)
    if needle_rgb is not None:
        h, w = min(needle_rgb.shape[0], out.shape[0] // 3), min(needle_rgb.shape[1], out.shape[1] // 3)
        out[:h, :w] = needle_rgb[:h, :w]
        out[h : h + 2, : w + 2] = 255
        out[: h + 2, w : w + 2] = 255
    return out


def _record(path: Path, view, belief: np.ndarray, picks, pose: np.ndarray) -> None:
    from earcore.app.recording import _rerun

    rr = _rerun()
    rec = rr.RecordingStream("earcore", recording_id="earcore-parts-show")
    rec.save(str(path))
    fx, fy, cx, cy = view.intrinsics
    h, w = view.rgb.shape[:2]
    rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
    rec.log("world/camera/image", rr.Pinhole(focal_length=[fx, fy], principal_point=[cx, cy], width=w, height=h), static=True)
    rec.log("world/camera/image/rgb", rr.Image(view.rgb))
    rec.log("world/camera/image/segmentation", rr.SegmentationImage((belief > 0.5).astype(np.uint8)))
    if picks:
        rec.log("world/camera/image/picks", rr.Points2D([p.pixel for p, _ in picks], colors=[(230, 20, 20)], radii=1.5))
        rec.log("world/picks", rr.Points3D([p.base for p, _ in picks], colors=[(230, 20, 20)], radii=0.006))
    rec.log("world/parts_truth", rr.Points3D(view.centres, colors=[(0, 200, 0)], radii=0.004))
    rec.flush()
    rec.disconnect()


def main(argv: list[str] | None = None, prog: str = "earcore parts show") -> int:
    args = _parser(prog).parse_args(argv)
    try:
        millimetres, degrees = (float(x) for x in args.calibration_error.split(","))
    except ValueError:
        return fail(prog, f"--calibration-error takes MM,DEG, got {args.calibration_error!r}")
    from earcore.errors import EarcoreError
    from earcore.learning import png
    from earcore.parts.find import detector_belief, oneshot_belief
    from earcore.parts.locate import locate_parts
    from earcore.pose.overlay import project
    from earcore.sim.part_station import PartStation, calibrated_pose

    needle_rgb: np.ndarray | None = None
    try:
        kind, model, meta = _load_model(args.model)
        classes = list(meta.get("classes") or [])
        if kind == "detector":
            if args.part is None:
                return fail(prog, f"{args.model} is a parts detector: name the type with --part (one of {', '.join(classes)})")
            if args.part not in classes:
                return fail(prog, f"unknown part type {args.part!r}; the detector knows {', '.join(classes)}")
            size = (model.options.width, model.options.height)
            wanted = args.part
        else:
            if args.part is not None:
                return fail(prog, f"{args.model} is a one-shot segmenter: give the part by one image (--needle-part or --needle)")
            size = args.size
            needle = _needle(args, classes, size, args.seed, model.divisor)
            crop = np.clip(np.rint(needle.image[:3].numpy().transpose(1, 2, 0) * 255), 0, 255).astype(np.uint8)
            needle_rgb = np.repeat(np.repeat(crop, SCALE - 1, axis=0), SCALE - 1, axis=1)
            wanted = args.needle_part
        with PartStation(width=size[0], height=size[1], seed=args.seed, classes=tuple(classes)) as station:
            index, view = _first_view(station, args.view, classes.index(wanted) if wanted in classes else None)
        pose = calibrated_pose(view.base_from_camera, millimetres, degrees, np.random.default_rng([args.seed, index]))
        depth = view.depth_mm if (model.options.in_channels == 4) else None
        if kind == "detector":
            belief = detector_belief(model, view.rgb, depth, classes.index(args.part))
        else:
            belief = oneshot_belief(model, needle, view.rgb, depth)
        picks = locate_parts(belief, view.depth_m, view.intrinsics, pose, min_pixels=args.min_pixels)
    except (EarcoreError, ValueError, OSError) as exc:
        return fail(prog, str(exc), 1)
    same = np.flatnonzero(view.classes == classes.index(wanted)) if wanted in classes else np.zeros(0, dtype=np.int64)
    camera_from_base = np.linalg.inv(view.base_from_camera)
    k = np.array([[view.intrinsics[0], 0, view.intrinsics[2]], [0, view.intrinsics[1], view.intrinsics[3]], [0, 0, 1.0]])
    truth_pixels = project(view.centres[same] @ camera_from_base[:3, :3].T + camera_from_base[:3, 3], k) if len(same) else np.zeros((0, 2))
    rows: list[dict[str, Any]] = []
    for pick, _ in picks:
        error = float(np.min(np.linalg.norm(view.centres[same] - pick.base, axis=1))) if len(same) else None
        rows.append(
            {
                "base_m": [round(float(x), 4) for x in pick.base],
                "pixel": [round(x, 1) for x in pick.pixel],
                "height_m": round(pick.height, 4),
                "pixels": pick.pixels,
                "error_m": None if error is None else round(error, 4),
            }
        )
    args.out.mkdir(parents=True, exist_ok=True)
    png.write(args.out / "show.png", _picture(view, belief, picks, truth_pixels, needle_rgb))
    summary = {"model": str(args.model), "network": kind, "part": wanted, "seed": args.seed, "view": index}
    summary |= {"parts_of_type": int(len(same)), "picks": rows}
    (args.out / "show.json").write_text(jsonfile.dumps(summary, indent=1) + "\n")
    if args.recording is not None:
        try:
            _record(args.recording, view, belief, picks, pose)
        except ImportError as exc:
            return fail(prog, str(exc), 1)
    label = wanted or "the needle's part"
    print(f"{label}: {len(picks)} found, {len(same)} on the platform (seed {args.seed}, view {index})")
    for (pick, _), r in zip(picks, rows):
        x, y, z = pick.base
        truth = "" if r["error_m"] is None else f", {1000 * r['error_m']:.1f} mm from the nearest true part"
        print(f"  pick at ({x:+.3f}, {y:+.3f}, {z:+.3f}) m in the base frame, {pick.pixels} px{truth}")
    print(f"picture: {args.out / 'show.png'}" + (f"; recording: {args.recording}" if args.recording else ""))
    return 0
