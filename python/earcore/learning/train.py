"""One training loop for every network: a model, an objective (batch → the model's
inputs, then batch + outputs → named losses), a loss combiner, datasets of dicts of
tensors and a `TrainConfig` → checkpoints, a metrics log, curves.

The run's folder holds `config.json`, `checkpoint.pt` (the latest; resuming continues
the same run: same batches, same random draws), `metrics.jsonl` and the curves. Runs
on the CPU by default with `config.threads` threads, on CUDA when asked (or `auto` and
present), and under torchrun as several processes (see `earcore.learning.distributed`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch
import torch.distributed as dist
from torch import Tensor

from earcore.errors import ConfigError, EarcoreError
from earcore.learning import distributed
from earcore.learning.checkpoint import CHECKPOINT_NAME, Checkpoint, CheckpointError, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from earcore.learning.combiners import LossCombiner
from earcore.learning.config import TrainConfig
from earcore.learning.metrics_log import MetricsLog, plot_metrics

__all__ = ["Objective", "TrainResult", "add_run_arguments", "collate", "run_command", "evaluate_losses", "resolve_device", "to_device", "train"]

Batch = dict[str, Tensor]


class Objective(Protocol):
    def inputs(self, batch: Batch) -> tuple[Tensor, ...]:
        """The model's positional inputs for a batch (usually `(batch["image"],)`)."""
        ...

    def losses(self, batch: Batch, outputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """Named scalar losses of a batch."""
        ...


#: (model, validation set, device, at most this many samples) → named metrics
Evaluator = Callable[[torch.nn.Module, Any, torch.device, "int | None"], Mapping[str, float]]


@dataclass
class TrainResult:
    folder: Path
    steps: int
    seconds: float
    evaluations: list[dict[str, float]] = field(default_factory=list)

    @property
    def last(self) -> dict[str, float]:
        return self.evaluations[-1] if self.evaluations else {}


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' was asked for but torch sees no CUDA device (use --device cpu or auto)")
    return torch.device(name)


def collate(items: Sequence[Mapping[str, Tensor]]) -> Batch:
    """Stack a list of samples (dicts of tensors) into a batch."""
    return {key: torch.stack([torch.as_tensor(item[key]) for item in items]) for key in items[0]}


def to_device(batch: Batch, device: torch.device) -> Batch:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


class _EpochView(torch.utils.data.Dataset):
    """Items addressed as (epoch, index) so that a dataset's per-epoch noise follows the
    epoch in worker processes too (they hold copies of the dataset)."""

    def __init__(self, dataset: Any):
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, key: tuple[int, int]) -> Mapping[str, Tensor]:
        epoch, index = key
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)
        return self.dataset[index]


def _batches(dataset: Any, sampler: distributed.EpochSampler, start: int, workers: int, pin: bool) -> Iterator[Batch]:
    keyed = ([(epoch, i) for i in chunk] for epoch, chunk in sampler.batches(start))
    loader = torch.utils.data.DataLoader(
        _EpochView(dataset),
        batch_sampler=keyed,
        num_workers=workers,
        collate_fn=collate,
        pin_memory=pin,
        generator=torch.Generator().manual_seed(sampler.seed),  # not the global generator: resuming must not shift its draws
    )
    return iter(loader)


def evaluate_losses(objective: Objective, combiner: LossCombiner, batch_size: int = 32) -> Evaluator:
    """An evaluator giving the mean of each loss (and the total) over the validation set."""

    def run(model: torch.nn.Module, dataset: Any, device: torch.device, limit: int | None) -> dict[str, float]:
        n = len(dataset) if limit is None else min(limit, len(dataset))
        sums: dict[str, float] = {}
        count = 0
        with torch.no_grad():
            for start in range(0, n, batch_size):
                batch = to_device(collate([dataset[i] for i in range(start, min(n, start + batch_size))]), device)
                losses = objective.losses(batch, model(*objective.inputs(batch)))
                total, _ = combiner(losses)
                size = batch["image"].shape[0]
                for k, v in {**losses, "total": total}.items():
                    sums[k] = sums.get(k, 0.0) + float(v) * size
                count += size
        return {f"val_{k}": v / max(count, 1) for k, v in sums.items()}

    return run


def _shared_losses(losses: Mapping[str, Tensor], world: distributed.World) -> dict[str, float]:
    """The step's losses for the combiner to learn from: every process's mean under
    DDP, so that learned weights stay the same in every process."""
    names = list(losses)
    values = torch.stack([losses[n].detach().float().reshape(()) for n in names])
    if world.distributed:
        values = values.to(next(iter(losses.values())).device)
        dist.all_reduce(values)
        values = values / world.size
    return dict(zip(names, values.cpu().tolist()))


def _optimiser(config: TrainConfig, params: list[torch.nn.Parameter]) -> torch.optim.Optimizer:
    if config.optimiser == "sgd":
        return torch.optim.SGD(params, lr=config.lr_start, momentum=config.momentum, weight_decay=config.weight_decay)
    if config.optimiser == "adamw":
        return torch.optim.AdamW(params, lr=config.lr_start, weight_decay=config.weight_decay)
    return torch.optim.Adam(params, lr=config.lr_start, weight_decay=config.weight_decay)


def _progress_bar(config: TrainConfig, start: int, enabled: bool) -> Any:
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=config.steps, initial=start, unit="step", dynamic_ncols=True, leave=True)


def train(
    model: torch.nn.Module,
    objective: Objective,
    train_set: Any,
    config: TrainConfig,
    folder: str | Path,
    *,
    combiner: LossCombiner,
    val_set: Any = None,
    evaluate: Evaluator | None = None,
    meta: Mapping[str, Any] | None = None,
    resume: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = print,
) -> TrainResult:
    """Train `model` until `config.steps` or `config.minutes`. `meta` is stored in the
    checkpoint (what is needed to rebuild the network). With `resume`, the run in
    `folder` continues from its checkpoint; without it, an existing checkpoint there is
    an error (nothing is overwritten)."""
    config.validate()
    folder = Path(folder)
    device = resolve_device(config.device)
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    world = distributed.init(device)
    say = log if (log is not None and world.main) else (lambda _: None)
    if len(train_set) < 1:
        raise ValueError("the training set is empty")
    if config.batch_size > len(train_set):
        raise ConfigError(f"batch_size {config.batch_size} is larger than the training set ({len(train_set)} samples); choose a batch of at most {len(train_set)}")

    path = folder / CHECKPOINT_NAME
    state: Checkpoint | None = None
    if path.exists():
        if not resume:
            raise ConfigError(f"{folder} already holds a run ({path.name}); resume it or choose another folder")
        state = load_checkpoint(path)
        if state.config is not None and state.config.get("network") != config.network:
            raise ConfigError(f"{path} was trained as {state.config.get('network')!r}, not {config.network!r}")

    best: dict[str, float] = {"value": float("inf"), "since": 0}  # the early stop's state (`patience`)
    torch.manual_seed(config.seed)
    model.to(device)
    combiner.to(device)
    params = [p for p in list(model.parameters()) + combiner.network_parameters() if p.requires_grad]
    if not params:
        raise ConfigError("nothing to train: every parameter of the network is frozen")
    optimiser = _optimiser(config, params)
    step, seconds = 0, 0.0
    if state is not None:
        try:
            model.load_state_dict(state.model)
        except RuntimeError as exc:  # torch lists every mismatching tensor: keep the first line
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise CheckpointError(f"{path} holds weights of another network shape than this run builds ({first.rstrip(':')})") from None
        if state.optimiser is not None:
            optimiser.load_state_dict(state.optimiser)
        if state.combiner:
            combiner.load_state_dict(state.combiner)
        if state.rng is not None:
            set_rng_state(state.rng)
        if state.patience is not None:
            best.update(state.patience)
        step, seconds = state.step, state.seconds
        say(f"resumed {folder} at step {step} ({seconds / 60:.1f} training minutes)")
    if world.main:
        config.save(folder / "config.json")
    net: torch.nn.Module = model
    if world.distributed:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    metrics = MetricsLog(folder / "metrics.jsonl", enabled=world.main)
    # A run that stopped without a checkpoint of its last steps (killed, crashed) logged
    # steps the resumed run does again: keep only what the checkpoint covers (a fresh
    # start in a folder without a checkpoint: nothing).
    dropped = metrics.keep_until(step if state is not None else -1)
    if dropped:
        say(f"dropped {dropped} metrics record(s) after step {step} (done again from the checkpoint)")
    evaluate = evaluate or evaluate_losses(objective, combiner)

    def checkpoint() -> None:
        if world.main:
            save_checkpoint(
                path,
                Checkpoint(
                    step=step,
                    seconds=seconds,
                    model=model.state_dict(),
                    optimiser=optimiser.state_dict(),
                    combiner=combiner.state_dict(),
                    rng=rng_state(),
                    config=config.to_dict(),
                    meta=dict(meta or {}),
                    patience=dict(best),
                ),
            )

    evaluations: list[dict[str, float]] = []

    def evaluation() -> None:
        if val_set is None or not world.main:
            return
        model.eval()
        try:
            started = time.perf_counter()
            values = dict(evaluate(model, val_set, device, config.eval_samples))
        finally:
            model.train()
        values["eval_seconds"] = time.perf_counter() - started
        evaluations.append({"step": step, "seconds": seconds, **values})
        metrics.write("eval", step, seconds, values)
        if config.patience is not None:
            if config.patience_metric not in values:
                raise ConfigError(f"patience watches {config.patience_metric!r}, which the evaluation does not give; it gives {', '.join(sorted(values))}")
            value = float(values[config.patience_metric])
            if value < best["value"]:
                best["value"], best["since"] = value, 0
            else:
                best["since"] += 1
        say(f"step {step} ({seconds / 60:.1f} min): " + ", ".join(f"{k} {v:.4g}" for k, v in values.items() if isinstance(v, float)))

    per_process = config.batch_size // world.size
    sampler = distributed.EpochSampler(len(train_set), config.batch_size, config.seed, world)
    batches = _batches(train_set, sampler, step, config.workers, pin=device.type == "cuda")
    bar = _progress_bar(config, step, progress and world.main)
    last_eval = (step, seconds)
    last_checkpoint = seconds
    sums: dict[str, float] = {}
    window = 0
    model.train()
    say(
        f"training {config.network} on {device} ({world.size} process(es), batch {config.batch_size}, {per_process} per process, "
        f"{len(train_set)} samples) into {folder}"
    )
    try:
        while True:
            rate = config.learning_rate(config.progress(step, seconds))
            stop = config.progress(step, seconds) >= 1.0 or (config.patience is not None and best["since"] >= config.patience)
            if world.distributed:  # rank 0's clock decides for everyone
                shared = torch.tensor([float(stop), rate], dtype=torch.float64, device=device)
                dist.broadcast(shared, 0)
                stop, rate = bool(shared[0] > 0.5), float(shared[1])
            if stop:
                break
            for group in optimiser.param_groups:
                group["lr"] = rate
            tick = time.perf_counter()
            batch = to_device(next(batches), device)
            outputs = net(*objective.inputs(batch))
            losses = objective.losses(batch, outputs)
            total, weights = combiner(losses)
            if not torch.isfinite(total):
                raise FloatingPointError(f"the loss became {float(total)} at step {step} ({ {k: float(v) for k, v in losses.items()} })")
            optimiser.zero_grad(set_to_none=True)
            total.backward()
            if world.distributed:  # DDP averages the model's gradients, not those of the combiner's parameters
                for p in combiner.network_parameters():
                    if p.grad is not None:
                        dist.all_reduce(p.grad)
                        p.grad.div_(world.size)
            if config.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(params, config.grad_clip)
            optimiser.step()
            combiner.update(_shared_losses(losses, world))
            step += 1
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds += time.perf_counter() - tick
            for k, v in {**losses, "total": total}.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
            window += 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{float(total):.4f}", lr=f"{rate:.1e}", refresh=False)
            if step % config.log_every == 0:
                values = {k: v / window for k, v in sums.items()}
                metrics.write("train", step, seconds, {**values, "lr": rate, **{f"w_{k}": w for k, w in weights.items()}})
                sums, window = {}, 0
            due = (config.eval_every_steps is not None and step - last_eval[0] >= config.eval_every_steps) or (
                config.eval_every_minutes is not None and seconds - last_eval[1] >= 60.0 * config.eval_every_minutes
            )
            if due:
                evaluation()
                last_eval = (step, seconds)
            if seconds - last_checkpoint >= 60.0 * config.checkpoint_every_minutes:
                checkpoint()
                last_checkpoint = seconds
    except KeyboardInterrupt:
        checkpoint()  # Ctrl-C keeps the steps done; resuming continues from here
        say(f"interrupted at step {step}; checkpoint {path} (resume to continue)")
        raise
    finally:
        if bar is not None:
            bar.close()
    checkpoint()
    if last_eval[0] != step or not evaluations:
        evaluation()
    if world.main:
        plot_metrics(folder / "metrics.jsonl")
    if config.patience is not None and best["since"] >= config.patience:
        say(f"stopped: {config.patience} evaluations without a better {config.patience_metric} (best {best['value']:.4g})")
    say(f"done: {step} steps in {seconds / 60:.1f} training minutes; checkpoint {path}")
    return TrainResult(folder=folder, steps=step, seconds=seconds, evaluations=evaluations)


def add_run_arguments(parser: Any, batches: str = "batches") -> None:
    """The options every trainer's command line shares: threads, data-loader workers,
    device, seed, resuming and the progress bar (`batches`: what the workers make)."""
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--workers", type=int, default=0, help=f"data-loader processes (default 0: {batches} are made in the training process)")
    parser.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")
    parser.add_argument("--no-progress", action="store_true")


def run_command(prog: str, call: Callable[[], Any]) -> int:
    """A trainer's command-line ending: `call()` (which returns a results table or None),
    its table printed; a setting that does not fit the data or the run exits 2, a bad
    dataset, damaged checkpoint or existing run 1, each with its message. Under
    torchrun the process then leaves the process group: with the others once it
    succeeded, at once when it failed (`distributed.shutdown`)."""
    code, table = 1, None
    try:
        table = call()
        code = 0
    except ConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        code = 2
    except (EarcoreError, ValueError, OSError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
    finally:
        distributed.shutdown(together=code == 0)
    if table is not None:
        print(table.markdown())
    return code
