"""Training a pose network on an earcore-images dataset, runnable from the source tree
with only Python, numpy and torch (no compiled core, no OpenCV, no matplotlib needed):

    PYTHONPATH=python python -m earcore.pose.train --data DATA --network multi --out runs/multi --minutes 60
    torchrun --nproc_per_node 2 -m earcore.pose.train --data DATA --out runs/multi ...   # DDP

The run folder gets config.json, checkpoint.pt, metrics.jsonl, curves (if matplotlib is
installed) and results.md / results.json (the test split's table, per robot).
`earcore train pose ...` is the same command through the earcore CLI.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from earcore.errors import ConfigError
from earcore.learning.checkpoint import CHECKPOINT_NAME, CheckpointError, load_checkpoint
from earcore.learning.combiners import COMBINERS, combiner_for
from earcore.learning.config import SCHEDULES, TrainConfig, key_values, load_config
from earcore.learning.freeze import freeze
from earcore.learning.train import TrainResult, run_command, train
from earcore.pose.evaluate import Evaluation, evaluate, evaluator, subset
from earcore.pose.networks import NETWORKS, PRESETS, PoseNetwork, build_network
from earcore.pose.objectives import default_weights, objective_for
from earcore.pose.transfer import TRAINABLE, trainable_modules, transfer_weights

#: What the periodic evaluation gives that `patience` can watch (lower is better).
PATIENCE_METRICS = ("joints_median_cm", "joints_mean_cm", "base_median_cm", "base_mean_cm")

__all__ = ["build_parser", "check_resume", "fit_statistics", "load_trained", "loss_weights", "main", "run"]


def fit_statistics(network: PoseNetwork, dataset: Any, samples: int = 256, seed: int = 0) -> None:
    """Set the network's output scaling (mean and spread of the keypoints and bases, per
    axis) and its camera (the median intrinsics) from `samples` images drawn at random
    across the set (the same for the same seed; datasets are stored one robot after
    another, so the first images would describe one robot)."""
    if len(dataset) < 1:
        raise ValueError("the training set is empty")
    points, intrinsics = [], []
    # A zoomed set's camera is its whole-image look's (what `estimate` scales to an image).
    look = getattr(dataset, "first_look", dataset.__getitem__)
    for i in subset(len(dataset), samples, seed).tolist():
        item = look(i)
        points.append(item["keypoints"][item["keypoint_valid"]])
        points.append(item["base"][None])
        intrinsics.append(item["intrinsics"])
    p = torch.cat(points).double()
    network.set_output_statistics(p.mean(0).float(), p.std(0).clamp(min=0.05).float() if len(p) > 1 else torch.full((3,), 0.5))
    network.set_camera(torch.stack(intrinsics).median(0).values)


def load_trained(path: str | Path, device: str | torch.device = "cpu") -> tuple[PoseNetwork, dict[str, Any]]:
    """A trained network (eval mode) and its checkpoint's meta (network, options,
    robots, keypoint names, input size) from a run folder or checkpoint file."""
    state = load_checkpoint(path)
    meta = state.meta
    if "network" not in meta or "options" not in meta:
        raise ConfigError(f"{path}: the checkpoint does not say which network it holds")
    network = build_network(meta["network"], meta["options"])
    try:
        network.load_state_dict(state.model)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1].strip() if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: the weights do not fit the network the checkpoint describes ({first})") from None
    return network.to(device).eval(), meta


def check_resume(out: Path, network: PoseNetwork) -> None:
    """A `CheckpointError` naming the options that differ when the run in `out` was
    trained with another network shape than `network` (another preset, --option, image
    size, keypoint or robot count) than resuming it would build."""
    path = out / CHECKPOINT_NAME
    if not path.exists():
        return
    stored = load_checkpoint(path).meta.get("options")
    if not isinstance(stored, dict):
        return
    ours = json.loads(json.dumps(network.options.to_dict()))
    theirs = json.loads(json.dumps(stored))
    differ = sorted(k for k in set(ours) | set(theirs) if ours.get(k) != theirs.get(k))
    if differ:
        what = ", ".join(f"{k} {theirs.get(k)!r} there, {ours.get(k)!r} now" for k in differ)
        raise CheckpointError(f"{path} holds a network with other options ({what}); resume with its options or train into another --out")


def loss_weights(network: str, given: dict[str, float]) -> dict[str, float]:
    """The network's default loss weights updated with `given`; a name the network's
    objective never produces (a typo) is a `ConfigError` naming the known ones."""
    defaults = default_weights(network)
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        names = ", ".join(map(repr, unknown))
        raise ConfigError(f"loss_weights: {names} {'is' if len(unknown) == 1 else 'are'} not a loss of the {network} network; its losses: {', '.join(defaults)}")
    return {**defaults, **given}


def build_parser(parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.pose.train") -> argparse.ArgumentParser:
    p = parser_class(prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="an earcore-images dataset folder")
    p.add_argument("--extra", type=Path, action="append", default=[], help="more training images: all of this folder (same image size), repeatable")
    p.add_argument(
        "--join",
        type=Path,
        action="append",
        default=[],
        help="another dataset, all its robots (--robots picks in --data): its train split joins the training images, its test split the test images; repeatable",
    )
    p.add_argument("--network", choices=NETWORKS, default=None, help="multi (Paper V, default), cascade (Paper IV) or keypoint")
    p.add_argument("--out", type=Path, required=True, help="the run folder (config, checkpoint, metrics, results)")
    p.add_argument("--preset", choices=sorted(PRESETS), default=None, help="network shape: small (shipped, default) or paper")
    p.add_argument("--minutes", type=float, default=None, help="training time budget (default 60 unless --steps)")
    p.add_argument("--steps", type=int, default=None, help="optimiser steps")
    p.add_argument("--batch", type=int, default=None, help="global batch size (default 64, Paper V)")
    p.add_argument("--lr", type=float, nargs=2, default=None, metavar=("START", "END"), help="learning rate from START to END (default 1e-3 1e-6)")
    p.add_argument("--schedule", choices=SCHEDULES, default=None, help="learning-rate schedule from START to END (default cosine)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--workers", type=int, default=None, help="data-loading worker processes (default 0)")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default=None)
    p.add_argument("--robots", nargs="*", default=None, help="train on these robots only")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--eval-minutes", type=float, default=None, help="evaluate on the test split every this many training minutes (default 5)")
    p.add_argument("--zoom", type=int, default=None, help="keypoint network: boxes around the robot from images this many times its input (2: 256x212 data)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=JSON", help="a network option, e.g. --option width=0.75 --option mask_stride=1")
    p.add_argument(
        "--transfer-from", type=Path, default=None, metavar="CHECKPOINT", help="start from this trained network (a run folder or checkpoint): what fits is kept"
    )
    p.add_argument("--trainable", default=None, help=f"which parts train: {', '.join(TRAINABLE)} (default all) or module paths, comma-separated")
    p.add_argument("--loss-combiner", choices=COMBINERS, default=None, help="how the losses become one total (default fixed: the papers' weights)")
    p.add_argument("--combiner-option", action="append", default=[], metavar="KEY=JSON", help="a combiner setting, e.g. --combiner-option lr=1e-3")
    p.add_argument("--train-samples", type=int, default=None, metavar="N", help="train on N images drawn at random from the training images")
    p.add_argument("--per-robot", action="store_true", help="--train-samples N images of each robot")
    p.add_argument("--patience", type=int, default=None, help="stop after this many evaluations without a lower joint error")
    p.add_argument("--config", type=Path, default=None, help="a TrainConfig JSON file (the command line's options override it)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    base: dict[str, Any] = {}
    if args.config is not None:
        base = load_config(args.config).to_dict()
    elif args.resume and (args.out / "config.json").is_file():
        base = load_config(args.out / "config.json").to_dict()
    changes: dict[str, Any] = {}
    for key, value in (
        ("network", args.network),
        ("batch_size", args.batch),
        ("schedule", args.schedule),
        ("threads", args.threads),
        ("workers", args.workers),
        ("device", args.device),
        ("seed", args.seed),
        ("eval_every_minutes", args.eval_minutes),
    ):
        if value is not None:
            changes[key] = value
    if args.lr is not None:
        changes["lr_start"], changes["lr_end"] = args.lr
    if args.transfer_from is not None:
        changes["transfer_from"] = str(args.transfer_from)
    if args.trainable is not None:
        parts = [t.strip() for t in args.trainable.split(",") if t.strip()]
        changes["trainable"] = parts[0] if len(parts) == 1 and parts[0] in TRAINABLE else parts
    if args.loss_combiner is not None:
        changes["loss_combiner"] = args.loss_combiner
    if args.combiner_option:
        changes["combiner_options"] = {**base.get("combiner_options", {}), **key_values(args.combiner_option, "--combiner-option")}
    if args.train_samples is not None:
        changes["train_samples"] = args.train_samples
    if args.per_robot:
        changes["samples_per_robot"] = True
    if args.patience is not None:
        changes["patience"] = args.patience
        if base.get("patience_metric", "val_total") == "val_total":  # the generic default: not a pose evaluation value
            changes["patience_metric"] = "joints_median_cm"
    if args.steps is not None or args.minutes is not None:
        changes["steps"], changes["minutes"] = args.steps, args.minutes
    options = dict(base.get("network_options", {}))
    if args.preset is not None:
        options.update(PRESETS[args.preset])
    elif not base:
        options.update(PRESETS["small"])
    options.update(key_values(args.option, "--option"))
    if args.zoom is not None:
        options["zoom"] = args.zoom
    changes["network_options"] = options
    notes = dict(base.get("notes", {}))
    notes.update(
        {
            "data": str(args.data),
            "extra": [str(e) for e in args.extra],
            "join": [str(j) for j in args.join],
            "robots": args.robots,
            "preset": args.preset or notes.get("preset", "small"),
        }
    )
    changes["notes"] = notes
    merged = {**base, **changes}
    if not base and "network" not in changes:
        merged["network"] = "multi"
    return TrainConfig.from_dict(merged)


def run(
    config: TrainConfig,
    data: Path,
    out: Path,
    *,
    robots: list[str] | None = None,
    extra: list[Path] | tuple[Path, ...] = (),
    join: list[Path] | tuple[Path, ...] = (),
    resume: bool = False,
    progress: bool = True,
    datasets: tuple[Any, Any] | None = None,
) -> tuple[TrainResult, Evaluation | None]:
    """Train `config.network` on `data`'s train split, every image of the `extra`
    folders and the train splits of the `join` folders; evaluate on the test splits of
    `data` and the `join` folders (`datasets`: a (train, test) pair of Datasets
    instead). `robots` picks among the images of `data` and `extra`; a joined folder
    brings all its robots."""
    weights = loss_weights(config.network, dict(config.loss_weights))
    if config.patience is not None and config.patience_metric not in PATIENCE_METRICS:
        raise ConfigError(f"patience_metric must be one of the evaluation's {', '.join(PATIENCE_METRICS)} (lower is better), got {config.patience_metric!r}")
    if datasets is None:
        from earcore.learning.dataset import ImageDataset, ImageDatasets  # the Dataset over the earcore-images format

        train_set: Any = ImageDataset(data, split="train", robots=robots, noise=True, seed=config.seed)
        test_set: Any = ImageDataset(data, split="test", robots=robots, noise=False, seed=config.seed)
        joined = [ImageDataset(f, split="train", noise=True, seed=config.seed + 101 + j) for j, f in enumerate(join)]
        more = [ImageDataset(e, split=None, robots=robots, noise=True, seed=config.seed + 1 + j) for j, e in enumerate(extra)]
        if joined or more:
            train_set = ImageDatasets([train_set, *joined, *more])
        if join:
            test_set = ImageDatasets([test_set, *(ImageDataset(f, split="test", noise=False, seed=config.seed) for f in join)])
    else:
        train_set, test_set = datasets
    if config.train_samples is not None:
        from earcore.learning.dataset import SampledImages

        try:
            train_set = SampledImages(train_set, config.train_samples, seed=config.seed, per_robot=config.samples_per_robot)
        except ValueError as exc:
            raise ConfigError(f"train_samples: {exc}") from None
    import earcore.learning.distributed as dist_env

    say = print if dist_env.from_environment().main else (lambda _: None)
    options = dict(config.network_options)
    source = load_checkpoint(config.transfer_from) if config.transfer_from is not None else None
    if source is not None:
        if source.meta.get("network") != config.network:
            raise ConfigError(f"{config.transfer_from} holds a {source.meta.get('network')} network; train it as --network {source.meta.get('network')}")
        shape = dict(source.meta.get("options", {}))
        from_data = ("input_size", "num_keypoints", "num_robots", "zoom")
        ignored = sorted(k for k, v in options.items() if k not in from_data and k in shape and shape[k] != v)
        if ignored:
            say(f"the network's shape comes from {config.transfer_from}; not used: {', '.join(f'{k}={options[k]!r}' for k in ignored)}")
        options = {**shape, **{k: v for k, v in options.items() if k == "zoom"}}  # the source's zoom unless --zoom says otherwise
    zoom = options.get("zoom", 1)
    if zoom != 1:
        from earcore.learning.dataset import ZoomedImages

        try:
            train_set = ZoomedImages(train_set, zoom, seed=config.seed)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    options["input_size"] = list(train_set.image_size)
    options["num_keypoints"] = int(train_set.num_keypoints)
    options["num_robots"] = len(train_set.robots)
    torch.manual_seed(config.seed)  # the initial weights follow the seed
    network = build_network(config.network, options)
    if resume:
        check_resume(Path(out), network)
    config = config.replace(network_options=network.options.to_dict())
    if source is None:
        fit_statistics(network, train_set, seed=config.seed)
    elif not (resume and (Path(out) / CHECKPOINT_NAME).exists()):  # the transferred network keeps its output scaling and camera
        say(f"transferred from {config.transfer_from}: {transfer_weights(network, source.model, source.meta, list(train_set.robots)).describe()}")
    frozen = freeze(network, trainable_modules(network, config.trainable))
    if config.trainable != "all":
        say(frozen.describe())
    manifest = getattr(train_set, "manifest", {})
    meta = {
        "network": config.network,
        "options": network.options.to_dict(),
        "robots": list(train_set.robots),
        "keypoints": manifest.get("keypoints", {}),
        "keypoint_frames": manifest.get("keypoint_frames", {}),
        "input_size": list(train_set.image_size),
        "data": str(data),
        "extra": [str(e) for e in extra],
        "join": [str(j) for j in join],
        "transferred_from": config.transfer_from,
    }
    combiner = combiner_for(config.loss_combiner, list(weights), fixed=weights, seed=config.seed, **config.combiner_options)
    result = train(
        network,
        objective_for(config.network, seed=config.seed),
        train_set,
        config,
        out,
        combiner=combiner,
        val_set=test_set if len(test_set) else None,
        evaluate=evaluator,
        meta=meta,
        resume=resume,
        progress=progress,
    )
    if not len(test_set):
        return result, None
    if not dist_env.from_environment().main:
        return result, None
    trained, _ = load_trained(out, "cpu")
    table = evaluate(trained, test_set, "cpu", robots=train_set.robots, keypoint_names=meta["keypoints"])
    table.save(out, "results", f"{config.network} after {result.steps} steps ({result.seconds / 60:.1f} training minutes), test split")
    return result, table


def main(argv: list[str] | None = None, parser_class: type[argparse.ArgumentParser] = argparse.ArgumentParser, prog: str = "python -m earcore.pose.train") -> int:
    parser = build_parser(parser_class, prog)
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        parser.error(str(exc))
    return run_command(
        prog, lambda: run(config, args.data, args.out, robots=args.robots, extra=args.extra, join=args.join, resume=args.resume, progress=not args.no_progress)[1]
    )


if __name__ == "__main__":
    raise SystemExit(main())
