"""`earcore train pose`, `earcore evaluate pose`, `earcore export pose`: the pose
networks' commands (torch needed: pip install 'earcore[learning]').

    earcore train pose --data DATA --network multi|cascade|keypoint --out RUN [--minutes M] [--steps N]
                       [--batch B] [--threads T] [--device cpu|cuda|auto] [--resume] [--config FILE] ...
    earcore evaluate pose --checkpoint RUN --data DATA [--split test] [--out DIR]
    earcore export pose --checkpoint RUN --out model.onnx

The training itself is `earcore.pose.train` (also runnable as `python -m earcore.pose.train`
where the compiled core is missing, e.g. on a GPU machine)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from earcore.app.arguments import Parser, fail, positive

#: How a refined table is titled.
REFINED_LABELS = {"fit": " + kinematic fit", "pnp": " + PnP with the joint angles known"}

__all__ = ["evaluate_main", "export_main", "train_main"]


def _pose_only(argv: list[str] | None, command: str) -> list[str] | int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(f"usage: earcore {command} pose ... (see earcore {command} pose --help)")
        return 0 if args else 2
    if args[0] != "pose":
        return fail(f"earcore {command}", f"unknown target {args[0]!r}; known: pose")
    return args[1:]


def train_main(argv: list[str] | None = None) -> int:
    rest = _pose_only(argv, "train")
    if isinstance(rest, int):
        return rest
    from earcore.errors import EarcoreError
    from earcore.pose.train import main

    try:
        return main(rest, Parser, "earcore train pose")
    except EarcoreError as exc:  # a bad dataset, a damaged checkpoint, an existing run
        return fail("earcore train pose", str(exc), 1)


def evaluate_main(argv: list[str] | None = None) -> int:
    rest = _pose_only(argv, "evaluate")
    if isinstance(rest, int):
        return rest
    parser = Parser(prog="earcore evaluate pose", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True, help="a run folder or checkpoint file")
    parser.add_argument("--data", type=Path, required=True, help="an earcore-images dataset folder")
    parser.add_argument("--split", choices=("train", "test", "all"), default="test")
    parser.add_argument("--robots", nargs="*", default=None)
    parser.add_argument("--out", type=Path, default=None, help="write results.md / results.json here (default: the run folder)")
    parser.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    parser.add_argument(
        "--refine",
        nargs="?",
        const="fit",
        choices=("fit", "pnp"),
        default=None,
        help="refine the keypoint network's 2D keypoints: fit the robot's kinematics (fit, the default) or PnP with the labels' joints (pnp)",
    )
    parser.add_argument(
        "--other-robots", action="store_true", help="evaluate images of robots the network does not know too (their type counts as wrong): what a network forgot"
    )
    args = parser.parse_args(rest)
    from earcore.errors import EarcoreError
    from earcore.learning.dataset import ImageDataset
    from earcore.learning.train import resolve_device
    from earcore.pose.evaluate import evaluate
    from earcore.pose.train import load_trained

    try:
        device = resolve_device(args.device)
        network, meta = load_trained(args.checkpoint, device)
        data = ImageDataset(args.data, split=None if args.split == "all" else args.split, robots=args.robots, noise=False)
        if tuple(data.image_size) != tuple(network.options.input_size):
            return fail("earcore evaluate pose", f"the data's images are {data.image_size}, the network takes {tuple(network.options.input_size)}")
        if len(data) == 0:
            return fail("earcore evaluate pose", f"no {args.split} images in {args.data}")
        table = evaluate(
            network, data, device, robots=meta.get("robots", data.robots), keypoint_names=meta.get("keypoints"), refined=args.refine, foreign=args.other_robots
        )
    except (EarcoreError, ValueError) as exc:
        return fail("earcore evaluate pose", str(exc), 1)
    out = args.out or (args.checkpoint if args.checkpoint.is_dir() else args.checkpoint.parent)
    stem = f"results-{args.split}" + (f"-{args.refine}" if args.refine else "")
    md, _ = table.save(out, stem, f"{meta['network']}{REFINED_LABELS.get(args.refine, '')}, {args.split} split of {args.data}")
    print(table.markdown())
    print(f"wrote {md} and its .json")
    return 0


def export_main(argv: list[str] | None = None) -> int:
    rest = _pose_only(argv, "export")
    if isinstance(rest, int):
        return rest
    parser = Parser(prog="earcore export pose", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True, help="a run folder or checkpoint file")
    parser.add_argument("--out", type=Path, required=True, help="the .onnx file (its sidecar .json is written beside it)")
    parser.add_argument("--tolerance", type=positive, default=1e-4, help="largest allowed difference between torch and onnxruntime (> 0)")
    args = parser.parse_args(rest)
    if args.out.suffix != ".onnx":
        parser.error(f"argument --out: must end in .onnx, got {args.out}")
    from earcore.errors import EarcoreError
    from earcore.pose.export import export_network
    from earcore.pose.train import load_trained

    try:
        network, meta = load_trained(args.checkpoint)
    except EarcoreError as exc:
        return fail("earcore export pose", str(exc), 1)
    sidecar = export_network(network, meta, args.out)
    worst = max(sidecar["parity"].values())
    size = args.out.stat().st_size / 1e6
    print(f"wrote {args.out} ({size:.1f} MB) and {args.out.with_suffix('.json').name}; onnxruntime parity: max |Δ| {worst:.2e}")
    if worst > args.tolerance:
        return fail("earcore export pose", f"onnxruntime differs from torch by {worst:.2e} > {args.tolerance:g}", 1)
    return 0
