"""Training the one-shot segmenter (AAMAS 2019) with two part types held out, runnable
from the source tree with only Python, numpy and torch:

    PYTHONPATH=python python -m earcore.parts.oneshot_train --haystacks DATA --needles NEEDLES \\
        --held-out Axis,Motor --out runs/oneshot --steps 3000
    earcore parts oneshot-train ... --tasks needle          # the paper's "only IoU" ablation

The tasks (each a soft IoU error but the last): "needle" the needle's type in the
haystack, "all" every part in the haystack with the gates off, "self" the needle in its
own image, "spread" the vector spread of the needles' filter responses. With one task
its weight is 1; with more, the loss combiner (default the paper's AuxNet, two hidden
layers of 64) weighs them. Evaluation on the held-out trials (`HeldOutTrials`: the
test split's haystacks that hold both held-out types); the run folder gets config.json,
checkpoint.pt, metrics.jsonl, curves and results.md / results.json.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from earcore import jsonfile
from earcore.errors import ConfigError
from earcore.learning import distributed
from earcore.learning.checkpoint import CheckpointError, load_checkpoint
from earcore.learning.combiners import COMBINERS, combiner_for
from earcore.learning.config import TrainConfig, key_values
from earcore.learning.errors import DatasetError
from earcore.learning.losses import soft_iou_error, vector_spread
from earcore.learning.train import TrainResult, add_run_arguments, run_command, train
from earcore.parts.dataset import PartImages
from earcore.parts.oneshot import LEGACY_OPTIONS, TASKS, OneShotSegmenter, build_oneshot
from earcore.parts.oneshot_data import MIN_PIXELS, HeldOutTrials, OneShotPairs, needles_by_class, split_classes, visible_pixels
from earcore.parts.oneshot_evaluate import OneShotEvaluation, evaluate, evaluator

__all__ = ["NETWORK", "OneShotObjective", "build_parser", "load_oneshot", "main", "run"]

NETWORK = "parts-oneshot"


class OneShotObjective:
    def __init__(self, tasks: Sequence[str]) -> None:
        self.tasks = tuple(tasks)

    def inputs(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, ...]:
        return (batch["needle"], batch["haystack"], batch["second"], batch["needle_mask"], batch["second_mask"])

    def losses(self, batch: Mapping[str, Tensor], outputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        out = {"needle": soft_iou_error(outputs["needle"], batch["target"])}
        if "all" in self.tasks:
            out["all"] = soft_iou_error(outputs["all"], batch["all"])
        if "self" in self.tasks:
            out["self"] = soft_iou_error(outputs["self"], batch["needle_mask"])
        if "spread" in self.tasks:
            cls = batch["cls"]
            out["spread"] = vector_spread(outputs["vector"], outputs["second"], cls[:, None] == cls[None, :])
        return out


def load_oneshot(path: str | Path, device: str | torch.device = "cpu") -> tuple[OneShotSegmenter, dict[str, Any]]:
    """A trained segmenter (eval mode) and its checkpoint's meta."""
    state = load_checkpoint(path)
    meta = state.meta
    if meta.get("network") != NETWORK or "options" not in meta:
        raise ConfigError(f"{path}: not a one-shot segmenter checkpoint (it holds {meta.get('network')!r})")
    model = build_oneshot(**{**LEGACY_OPTIONS, **meta["options"]})
    weights = dict(state.model)
    weights.setdefault("log_sharpness", model.log_sharpness.detach().clone())  # older checkpoints: power 1
    try:
        model.load_state_dict(weights)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: the weights do not fit the segmenter the checkpoint describes ({first})") from None
    return model.to(device).eval(), meta


def build_parser(
    parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.parts.oneshot_train"
) -> argparse.ArgumentParser:
    p = parser_class(prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--haystacks", type=Path, required=True, help="a parts dataset of several parts per image")
    p.add_argument("--needles", type=Path, required=True, help="a parts dataset of one part per image (--objects 1-1)")
    p.add_argument("--held-out", required=True, help="comma-separated part types never trained on, e.g. Axis,Motor")
    p.add_argument("--out", type=Path, required=True, help="the run folder")
    p.add_argument("--tasks", default=",".join(TASKS), help=f"comma-separated, from {', '.join(TASKS)} (default all four)")
    p.add_argument("--rgb", action="store_true", help="colour only (the paper's best); default RGB-D")
    p.add_argument("--option", action="append", default=[], metavar="KEY=JSON", help="a network option, e.g. --option widths=[8,16,32,64]")
    p.add_argument("--steps", type=int, default=None, help="optimiser steps")
    p.add_argument("--minutes", type=float, default=None, help="training time budget (default 30 unless --steps)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, nargs=2, default=(1e-3, 1e-3), metavar=("START", "END"), help="learning rate (default 1e-3 constant)")
    p.add_argument("--loss-combiner", choices=COMBINERS, default="auxnet", help="how several tasks become one loss (default auxnet)")
    p.add_argument("--combiner-option", action="append", default=[], metavar="KEY=JSON")
    p.add_argument("--eval-steps", type=int, default=100, help="evaluate on the held-out trials every this many steps")
    p.add_argument("--eval-samples", type=int, default=None, help="at most this many trials per evaluation (default all)")
    add_run_arguments(p, "pairs")
    return p


def parse_tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or "needle" not in tasks:
        raise ConfigError(f"--tasks takes names from {', '.join(TASKS)} and must include needle, got {text!r}")
    return tasks


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    tasks = parse_tasks(args.tasks)
    options = {"tasks": list(tasks), "in_channels": 3 if args.rgb else 4, **key_values(args.option, "--option")}
    minutes = args.minutes if (args.minutes is not None or args.steps is not None) else 30.0
    combiner = args.loss_combiner if len(tasks) > 1 else "fixed"
    combiner_options = key_values(args.combiner_option, "--combiner-option")
    if combiner == "auxnet":
        combiner_options = {"hidden": 64, **combiner_options}
    return TrainConfig(
        network=NETWORK,
        network_options=options,
        steps=args.steps,
        minutes=minutes,
        batch_size=args.batch,
        lr_start=args.lr[0],
        lr_end=args.lr[1],
        schedule="constant" if args.lr[0] == args.lr[1] else "cosine",
        loss_weights={t: 1.0 for t in tasks},
        loss_combiner=combiner,
        combiner_options=combiner_options,
        device=args.device,
        threads=args.threads,
        workers=args.workers,
        seed=args.seed,
        eval_every_steps=args.eval_steps,
        eval_every_minutes=None,
        eval_samples=args.eval_samples,
        notes={"haystacks": str(args.haystacks), "needles": str(args.needles), "held_out": args.held_out},
    ).validate()


def run(
    config: TrainConfig,
    haystacks: Path,
    needles: Path,
    held_out: Sequence[str],
    out: Path,
    *,
    resume: bool = False,
    progress: bool = True,
    log: Any = print,
) -> tuple[TrainResult, OneShotEvaluation | None]:
    """Train on the seen types' pairs, evaluate on the held-out trials."""
    depth = int(config.network_options.get("in_channels", 4)) == 4
    torch.manual_seed(config.seed)
    model = build_oneshot(**config.network_options)
    divisor = model.divisor
    train_hay = PartImages(haystacks, split="train", noise=True, seed=config.seed)
    seen, unseen = split_classes(train_hay.classes, held_out)
    pairs = OneShotPairs(train_hay, PartImages(needles, split="train", noise=False), seen, depth=depth, seed=config.seed, divisor=divisor)
    test_hay, all_needles = PartImages(haystacks, split="test", noise=False), PartImages(needles, split=None, noise=False)
    trials = HeldOutTrials(test_hay, all_needles, unseen, depth=depth, seed=config.seed, divisor=divisor)
    config = config.replace(network_options=model.options.to_dict())
    tasks = model.options.tasks
    combiner = combiner_for(config.loss_combiner, list(tasks), fixed=dict(config.loss_weights), seed=config.seed, **config.combiner_options)
    meta = {"network": NETWORK, "options": model.options.to_dict(), "classes": train_hay.classes, "held_out": [train_hay.classes[c] for c in unseen]}
    result = train(
        model,
        OneShotObjective(tasks),
        pairs,
        config,
        out,
        combiner=combiner,
        val_set=trials,
        evaluate=evaluator(),
        meta=meta,
        resume=resume,
        progress=progress,
        log=log,
    )
    if not distributed.from_environment().main:
        return result, None  # under torchrun only rank 0 evaluates and writes
    trained, _ = load_oneshot(out)
    table = evaluate(trained, trials)
    text = f"One-shot segmenter after {result.steps} steps ({result.seconds / 60:.1f} training minutes)\n\n" + table.markdown()
    summary = table.to_dict()
    seen_trials = _seen_trials(haystacks, needles, seen, depth, config.seed, divisor)
    if seen_trials is not None:
        # the same protocol on two trained types (needles not trained on): separates a model that
        # has not learnt to follow the needle from one that does not carry it over to new types
        known = evaluate(trained, seen_trials, kind="trained")
        summary["seen"] = known.to_dict()
        text += "\nThe same trials on two trained types (test-split needles and haystacks):\n\n" + known.markdown()
    Path(out, "results.md").write_text(text)
    Path(out, "results.json").write_text(jsonfile.dumps(summary, indent=1) + "\n")
    return result, table


def _seen_trials(haystacks: Path, needles: Path, seen: Sequence[int], depth: bool, seed: int, divisor: int) -> HeldOutTrials | None:
    """Trials of the two trained types most often seen together in the test split, with
    test-split needles; None when no test haystack shows two of them."""
    test = PartImages(haystacks, split="test", noise=False)
    test_needles = PartImages(needles, split="test", noise=False)
    visible = visible_pixels(test) >= MIN_PIXELS
    try:
        usable = sorted(needles_by_class(test_needles, seen, every=False))
    except DatasetError:
        return None
    together = [(int((visible[:, a] & visible[:, b]).sum()), a, b) for i, a in enumerate(usable) for b in usable[i + 1 :]]
    best = max(together, default=(0, 0, 0))
    if best[0] == 0:
        return None
    return HeldOutTrials(test, test_needles, best[1:], depth=depth, seed=seed, divisor=divisor)


def main(
    argv: list[str] | None = None, parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.parts.oneshot_train"
) -> int:
    parser = build_parser(parser_class, prog)
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        parser.error(str(exc))
    held_out = [h.strip() for h in args.held_out.split(",") if h.strip()]
    return run_command(prog, lambda: run(config, args.haystacks, args.needles, held_out, args.out, resume=args.resume, progress=not args.no_progress)[1])


if __name__ == "__main__":
    raise SystemExit(main())
