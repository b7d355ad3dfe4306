"""Training the parts detector (IROS 2018) on a parts dataset, runnable from the source
tree with only Python, numpy and torch:

    PYTHONPATH=python python -m earcore.parts.train --data DATA --out runs/parts --steps 2000
    earcore parts train --data DATA --out runs/parts --loss-combiner auxnet

The losses are "iou" (soft IoU error) and "distance" (pickup-point centroid, px); how
they become one total is the loss combiner: "fixed" with --weights (the paper's
"distance only" is iou=0, "IoU only" distance=0, their sum iou=1,distance=1), "kgc",
"kgc-eps", "kgc-mean", "auxnet", ... (`earcore.learning.combiners`). The run folder
gets config.json, checkpoint.pt, metrics.jsonl, curves and results.md / results.json
(pickup rate, distance and IoU per part type on the test split).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch

from earcore import jsonfile
from earcore.errors import ConfigError
from earcore.learning import distributed
from earcore.learning.checkpoint import CheckpointError, load_checkpoint
from earcore.learning.combiners import COMBINERS, combiner_for
from earcore.learning.config import SCHEDULES, TrainConfig, key_values
from earcore.learning.train import TrainResult, add_run_arguments, run_command, train
from earcore.parts.dataset import PartImages
from earcore.parts.detector import PRESETS, PartDetector, build_detector
from earcore.parts.evaluate import PartsEvaluation, evaluate, evaluator
from earcore.parts.objective import LOSSES, DetectorObjective

__all__ = ["build_parser", "load_detector", "main", "run"]

NETWORK = "parts-detector"
#: The evaluation values `patience` may watch (lower is better).
PATIENCE_METRICS = ("val_combined", "val_pickup_error", "val_iou_error", "val_distance_px", "val_distance_cm")


def load_detector(path: str | Path, device: str | torch.device = "cpu") -> tuple[PartDetector, dict[str, Any]]:
    """A trained detector (eval mode) and its checkpoint's meta (classes, options)."""
    state = load_checkpoint(path)
    meta = state.meta
    if meta.get("network") != NETWORK or "options" not in meta:
        raise ConfigError(f"{path}: not a parts detector checkpoint (it holds {meta.get('network')!r})")
    options = dict(meta["options"])
    detector = build_detector(options.pop("classes"), options.pop("width"), options.pop("height"), "small", **options)
    try:
        detector.load_state_dict(state.model)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: the weights do not fit the detector the checkpoint describes ({first})") from None
    return detector.to(device).eval(), meta


def build_parser(parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.parts.train") -> argparse.ArgumentParser:
    p = parser_class(prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="a parts dataset folder (earcore parts generate)")
    p.add_argument("--out", type=Path, required=True, help="the run folder")
    p.add_argument("--preset", choices=sorted(PRESETS), default="small", help="detector shape: small (default) or paper")
    p.add_argument("--option", action="append", default=[], metavar="KEY=JSON", help="a detector option, e.g. --option widths=[8,16,32,64]")
    p.add_argument("--steps", type=int, default=None, help="optimiser steps")
    p.add_argument("--minutes", type=float, default=None, help="training time budget (default 30 unless --steps)")
    p.add_argument("--batch", type=int, default=8, help="batch size (default 8, the paper's)")
    p.add_argument("--lr", type=float, nargs=2, default=(1e-3, 1e-5), metavar=("START", "END"), help="learning rate from START to END (default 1e-3 1e-5)")
    p.add_argument("--schedule", choices=SCHEDULES, default="cosine")
    p.add_argument("--loss-combiner", choices=COMBINERS, default="fixed", help="how the two losses become one (default fixed: --weights)")
    p.add_argument("--weights", default="iou=1,distance=0.05", help="fixed weights, e.g. iou=1,distance=0 (IoU only); default iou=1,distance=0.05")
    p.add_argument("--combiner-option", action="append", default=[], metavar="KEY=JSON", help="a combiner setting, e.g. --combiner-option lr=1e-3")
    p.add_argument("--distance-unit", type=float, default=1.0, help="pixels per unit of the distance loss (the paper's KGC: 100)")
    p.add_argument("--eval-steps", type=int, default=None, help="evaluate every this many steps (default: every 2 minutes)")
    p.add_argument("--eval-samples", type=int, default=256, help="test images per periodic evaluation (default 256)")
    p.add_argument("--patience", type=int, default=None, help="stop after this many evaluations without a lower --patience-metric")
    p.add_argument("--patience-metric", choices=PATIENCE_METRICS, default="val_combined")
    add_run_arguments(p)
    return p


def parse_weights(text: str) -> dict[str, float]:
    weights: dict[str, float] = {}
    for item in (t for t in text.split(",") if t.strip()):
        name, sep, value = item.partition("=")
        if not sep or name.strip() not in LOSSES:
            raise ConfigError(f"--weights takes NAME=VALUE with names {', '.join(LOSSES)}, got {item!r}")
        try:
            weights[name.strip()] = float(value)
        except ValueError:
            raise ConfigError(f"--weights: {item!r} is not a number") from None
    missing = [n for n in LOSSES if n not in weights]
    if missing:
        raise ConfigError(f"--weights must give every loss ({', '.join(LOSSES)}); missing {', '.join(missing)}")
    return weights


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    options = {**PRESETS[args.preset], **key_values(args.option, "--option")}
    minutes = args.minutes if (args.minutes is not None or args.steps is not None) else 30.0
    return TrainConfig(
        network=NETWORK,
        network_options={k: list(v) if isinstance(v, tuple) else v for k, v in options.items()},
        steps=args.steps,
        minutes=minutes,
        batch_size=args.batch,
        lr_start=args.lr[0],
        lr_end=args.lr[1],
        schedule=args.schedule,
        loss_weights=parse_weights(args.weights),
        loss_combiner=args.loss_combiner,
        combiner_options=key_values(args.combiner_option, "--combiner-option"),
        patience=args.patience,
        patience_metric=args.patience_metric,
        device=args.device,
        threads=args.threads,
        workers=args.workers,
        seed=args.seed,
        eval_every_steps=args.eval_steps,
        eval_every_minutes=None if args.eval_steps is not None else 2.0,
        eval_samples=args.eval_samples,
        notes={"data": str(args.data), "preset": args.preset, "distance_unit": args.distance_unit},
    ).validate()


def run(
    config: TrainConfig, data: Path, out: Path, *, distance_unit: float = 1.0, resume: bool = False, progress: bool = True, log: Any = print
) -> tuple[TrainResult, PartsEvaluation | None]:
    """Train the detector on `data`'s train split, evaluate on its test split."""
    if config.patience is not None and config.patience_metric not in PATIENCE_METRICS:
        raise ConfigError(f"patience_metric must be one of {', '.join(PATIENCE_METRICS)}, got {config.patience_metric!r}")
    train_set = PartImages(data, split="train", noise=True, seed=config.seed)
    test_set = PartImages(data, split="test", noise=False, seed=config.seed)
    w, h = train_set.image_size
    torch.manual_seed(config.seed)
    options = dict(config.network_options)
    detector = build_detector(len(train_set.classes), w, h, "small", **options)
    config = config.replace(network_options={k: v for k, v in detector.options.to_dict().items() if k not in ("classes", "width", "height")})
    weights = dict(config.loss_weights)
    combiner = combiner_for(config.loss_combiner, list(LOSSES), fixed=weights, seed=config.seed, **config.combiner_options)
    meta = {"network": NETWORK, "options": detector.options.to_dict(), "classes": train_set.classes, "data": str(data), "distance_unit": distance_unit}
    result = train(
        detector,
        DetectorObjective(distance_unit),
        train_set,
        config,
        out,
        combiner=combiner,
        val_set=test_set if len(test_set) else None,
        evaluate=evaluator(),
        meta=meta,
        resume=resume,
        progress=progress,
        log=log,
    )
    if not len(test_set) or not distributed.from_environment().main:
        return result, None  # under torchrun only rank 0 evaluates and writes
    trained, _ = load_detector(out)
    table = evaluate(trained, test_set, train_set.classes)
    Path(out, "results.md").write_text(f"Parts detector after {result.steps} steps ({result.seconds / 60:.1f} training minutes), test split\n\n" + table.markdown())
    Path(out, "results.json").write_text(jsonfile.dumps(table.to_dict(), indent=1) + "\n")
    return result, table


def main(argv: list[str] | None = None, parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.parts.train") -> int:
    parser = build_parser(parser_class, prog)
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        parser.error(str(exc))
    return run_command(prog, lambda: run(config, args.data, args.out, distance_unit=args.distance_unit, resume=args.resume, progress=not args.no_progress)[1])


if __name__ == "__main__":
    raise SystemExit(main())
