"""`earcore parts`: parts on the table (IROS 2018 / AAMAS 2019).

    earcore parts generate --out data/parts --count 2000            # labelled RGB-D images
    earcore parts train --data data/parts --out runs/parts --steps 3000 [--loss-combiner auxnet]
    earcore parts evaluate --checkpoint runs/parts --data data/parts [--split test]
    earcore parts oneshot-train --haystacks data/parts --needles data/needles --held-out Axis,Motor --out runs/oneshot
    earcore parts show --model runs/parts --part Motor                      # find it, pick it in the base frame

`earcore dataset parts` is `earcore parts generate`. Rerunning a generation completes
its missing shards; a folder made with other options is refused.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from earcore.app.arguments import Parser, count, fail, positive_int

__all__ = ["evaluate_main", "generate_main", "main"]


def _size(text: str) -> tuple[int, int]:
    from earcore.app.dataset import _size as size

    return size(text)


def _range(text: str) -> tuple[int, int]:
    try:
        lo, _, hi = text.partition("-")
        out = (int(lo), int(hi or lo))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN-MAX such as 2-12, got {text!r}") from None
    return out


def generate_main(argv: list[str] | None = None, prog: str = "earcore parts generate") -> int:
    from earcore.app.dataset import render
    from earcore.parts.catalogue import part_names
    from earcore.sim.part_images import PartImageOptions
    from earcore.validate import ConfigError

    parser = Parser(prog=prog, description="Labelled RGB-D images of parts on a platform (docs/parts.md).")
    parser.add_argument("--out", type=Path, required=True, help="the dataset folder (created; resumed if it exists)")
    parser.add_argument("--count", type=positive_int, default=2000, help="images (default 2000)")
    parser.add_argument("--size", type=_size, default=(128, 96), help="image WIDTHxHEIGHT (default 128x96; the papers: 256x192)")
    parser.add_argument("--classes", default=",".join(part_names()), help="comma-separated part types, class order (default: all 13)")
    parser.add_argument("--objects", type=_range, default=(2, 12), help="parts per image MIN-MAX (default 2-12; 1 for single-part images)")
    parser.add_argument("--tray", type=float, default=0.3, help="probability of a tray around the parts (default 0.3)")
    parser.add_argument("--seed", type=count, default=0)
    parser.add_argument("--shard-size", type=positive_int, default=256)
    parser.add_argument("--workers", type=positive_int, default=None, help="worker processes (default: one per core)")
    parser.add_argument("--ray", action="store_true", help="render the shards as Ray tasks")
    parser.add_argument("--ray-address", default="auto")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    width, height = args.size
    try:
        options = PartImageOptions(
            classes=tuple(c.strip() for c in args.classes.split(",") if c.strip()),
            count=args.count,
            width=width,
            height=height,
            seed=args.seed,
            objects=args.objects,
            tray=args.tray,
            shard_size=args.shard_size,
        ).validate()
    except ConfigError as exc:
        return fail(prog, str(exc))
    return render(prog, "earcore.sim.part_images", options, args.out, args.workers, args.ray, args.ray_address, args.quiet)


def train_main(argv: list[str] | None = None) -> int:
    from earcore.errors import EarcoreError
    from earcore.parts.train import main

    try:
        return main(argv, Parser, "earcore parts train")
    except EarcoreError as exc:
        return fail("earcore parts train", str(exc), 1)


def evaluate_main(argv: list[str] | None = None) -> int:
    prog = "earcore parts evaluate"
    parser = Parser(prog=prog, description="Pickup rate, distance and IoU per part type of a trained detector.")
    parser.add_argument("--checkpoint", type=Path, required=True, help="a run folder or checkpoint file")
    parser.add_argument("--data", type=Path, required=True, help="a parts dataset folder")
    parser.add_argument("--split", choices=["train", "test", "all"], default="test")
    parser.add_argument("--limit", type=positive_int, default=None, help="at most this many images")
    parser.add_argument("--out", type=Path, default=None, help="write results.md and results.json here")
    args = parser.parse_args(argv)
    from earcore import jsonfile
    from earcore.errors import EarcoreError
    from earcore.parts.dataset import PartImages
    from earcore.parts.evaluate import evaluate
    from earcore.parts.train import load_detector

    try:
        detector, meta = load_detector(args.checkpoint)
        data = PartImages(args.data, split=None if args.split == "all" else args.split, noise=False)
        if data.classes != meta["classes"]:
            return fail(prog, f"{args.data} has part types {data.classes}, the detector was trained on {meta['classes']}")
        trained = (meta["options"]["width"], meta["options"]["height"])
        if tuple(data.image_size) != tuple(trained):
            return fail(prog, f"{args.data} holds {data.image_size[0]}×{data.image_size[1]} images, the detector takes {trained[0]}×{trained[1]}")
        table = evaluate(detector, data, data.classes, limit=args.limit)
    except (EarcoreError, ValueError, OSError) as exc:
        return fail(prog, str(exc), 1)
    print(table.markdown())
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.md").write_text(table.markdown())
        (args.out / "results.json").write_text(jsonfile.dumps(table.to_dict(), indent=1) + "\n")
    return 0


def oneshot_train_main(argv: list[str] | None = None) -> int:
    from earcore.errors import EarcoreError
    from earcore.parts.oneshot_train import main

    try:
        return main(argv, Parser, "earcore parts oneshot-train")
    except EarcoreError as exc:
        return fail("earcore parts oneshot-train", str(exc), 1)


def show_main(argv: list[str] | None = None) -> int:
    from earcore.app.parts_show import main

    return main(argv)


COMMANDS = {"generate": generate_main, "train": train_main, "evaluate": evaluate_main, "oneshot-train": oneshot_train_main, "show": show_main}


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if args else 2
    if args[0] not in COMMANDS:
        return fail("earcore parts", f"unknown command {args[0]!r}; known: {', '.join(COMMANDS)}")
    return COMMANDS[args[0]](args[1:])
