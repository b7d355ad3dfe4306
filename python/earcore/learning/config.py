"""One typed configuration per training run: `TrainConfig`, validated on creation,
written as JSON beside the run's checkpoints (`config.json`) and read back from it.
A key the class does not know is refused with its name, so a typo never trains
silently with a default."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import earcore.validate as validate  # not `from earcore import`: without the core, the package's __getattr__ answers first
from earcore.errors import ConfigError

__all__ = ["TrainConfig", "key_values", "load_config"]

OPTIMISERS = ("adam", "adamw", "sgd")
SCHEDULES = ("exponential", "cosine", "linear", "constant")
DEVICES = ("cpu", "cuda", "auto")


@dataclass
class TrainConfig:
    """What a run trains, for how long and how. Lengths: the run stops at `steps`
    optimiser steps or after `minutes` of training (evaluation excluded), whichever
    comes first; at least one of them must be set. The learning rate falls from
    `lr_start` to `lr_end` over the run's progress (the larger of the step and the
    time fraction), so a time-limited run still ends at `lr_end` (the papers:
    1e-3 → 1e-6, "decreased gradually"). The default is `cosine`: at equal steps it beat
    `exponential` (a straight line in log lr, which spends most of a run below 1e-4) on
    every metric (benches/RESULTS.md)."""

    network: str = "multi"
    #: the network's own options (widths, input size, ...), checked by the network's builder
    network_options: dict[str, Any] = field(default_factory=dict)
    steps: int | None = None
    minutes: float | None = 60.0
    batch_size: int = 64
    lr_start: float = 1e-3
    lr_end: float = 1e-6
    schedule: str = "cosine"
    optimiser: str = "adam"
    momentum: float = 0.9
    weight_decay: float = 0.0
    grad_clip: float | None = None
    #: named loss → weight (missing names take the network's defaults)
    loss_weights: dict[str, float] = field(default_factory=dict)
    #: how the losses become one total (`earcore.learning.combiners.COMBINERS`; "fixed": `loss_weights`)
    loss_combiner: str = "fixed"
    #: the combiner's own settings (decay, warmup, period, temperature, hidden, lr)
    combiner_options: dict[str, Any] = field(default_factory=dict)
    #: which parts of the network train: a named set of the network's or module paths ("all": everything)
    trainable: str | list[str] = "all"
    #: start from this trained network's weights (a run folder or checkpoint)
    transfer_from: str | None = None
    #: train on this many images drawn at random from the training set (None: all)
    train_samples: int | None = None
    #: `train_samples` images of each robot instead
    samples_per_robot: bool = False
    #: stop once this many evaluations in a row brought no new best `patience_metric` (None: never)
    patience: int | None = None
    #: the evaluation value `patience` watches; lower is better
    patience_metric: str = "val_total"
    device: str = "cpu"
    threads: int | None = None
    workers: int = 0
    seed: int = 0
    log_every: int = 10
    eval_every_steps: int | None = None
    eval_every_minutes: float | None = 5.0
    #: at most this many validation samples per evaluation (None: all)
    eval_samples: int | None = 512
    checkpoint_every_minutes: float = 5.0
    #: anything else the caller wants recorded with the run (dataset path, robots, ...)
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> TrainConfig:
        """Check every field; raises `ConfigError` naming the first bad one."""
        if not isinstance(self.network, str) or not self.network:
            raise ConfigError(f"network must be a non-empty name, got {self.network!r}")
        for name in ("network_options", "loss_weights", "combiner_options", "notes"):
            if not isinstance(getattr(self, name), dict):
                raise ConfigError(f"{name} must be a mapping, got {getattr(self, name)!r}")
        if self.steps is None and self.minutes is None:
            raise ConfigError("steps or minutes must be set (the run needs an end)")
        if self.steps is not None:
            validate.count(self.steps, "steps")
        if self.minutes is not None:
            validate.positive(self.minutes, "minutes", at_most=7 * 24 * 60)
        validate.count(self.batch_size, "batch_size")
        validate.positive(self.lr_start, "lr_start", at_most=10.0)
        validate.positive(self.lr_end, "lr_end", at_most=10.0)
        if self.lr_end > self.lr_start:
            raise ConfigError(f"lr_end must be <= lr_start, got {self.lr_end:g} > {self.lr_start:g}")
        validate.one_of(self.schedule, SCHEDULES, "schedule")
        validate.one_of(self.optimiser, OPTIMISERS, "optimiser")
        validate.fraction(self.momentum, "momentum")
        validate.non_negative(self.weight_decay, "weight_decay")
        if self.grad_clip is not None:
            validate.positive(self.grad_clip, "grad_clip")
        for key, weight in self.loss_weights.items():
            if not isinstance(key, str):
                raise ConfigError(f"loss_weights keys must be loss names, got {key!r}")
            validate.non_negative(weight, f"loss_weights[{key!r}]")
        if not isinstance(self.loss_combiner, str) or not self.loss_combiner:
            raise ConfigError(f"loss_combiner must be a name, got {self.loss_combiner!r}")
        if not (isinstance(self.trainable, str) or (isinstance(self.trainable, list) and self.trainable and all(isinstance(t, str) for t in self.trainable))):
            raise ConfigError(f"trainable must be a name or a non-empty list of module paths, got {self.trainable!r}")
        if self.transfer_from is not None and (not isinstance(self.transfer_from, str) or not self.transfer_from):
            raise ConfigError(f"transfer_from must be a path, got {self.transfer_from!r}")
        if self.patience is not None:
            validate.count(self.patience, "patience")
        if self.train_samples is not None:
            validate.count(self.train_samples, "train_samples")
        if not isinstance(self.samples_per_robot, bool):
            raise ConfigError(f"samples_per_robot must be true or false, got {self.samples_per_robot!r}")
        if not isinstance(self.patience_metric, str) or not self.patience_metric:
            raise ConfigError(f"patience_metric must be a name, got {self.patience_metric!r}")
        validate.one_of(self.device, DEVICES, "device")
        if self.threads is not None:
            validate.count(self.threads, "threads")
            if self.threads > 1024:
                raise ConfigError(f"threads must be at most 1024, got {self.threads}")
        validate.count(self.workers, "workers", minimum=0)
        validate.count(self.seed, "seed", minimum=0)
        validate.count(self.log_every, "log_every")
        if self.eval_every_steps is not None:
            validate.count(self.eval_every_steps, "eval_every_steps")
        if self.eval_every_minutes is not None:
            validate.positive(self.eval_every_minutes, "eval_every_minutes")
        if self.eval_samples is not None:
            validate.count(self.eval_samples, "eval_samples")
        validate.positive(self.checkpoint_every_minutes, "checkpoint_every_minutes")
        try:
            json.dumps(self.to_dict(), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"the configuration must be plain JSON (numbers, strings, lists, mappings): {exc}") from None
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with some fields changed (unknown names refused)."""
        return TrainConfig.from_dict({**self.to_dict(), **changes})

    @classmethod
    def from_dict(cls, data: Any) -> TrainConfig:
        if not isinstance(data, dict):
            raise ConfigError(f"a training configuration must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown training setting(s) {', '.join(map(repr, unknown))}; known: {', '.join(sorted(known))}")
        return cls(**data)

    def save(self, path: str | Path) -> Path:
        """Write as JSON (to a temporary, then renamed, so a reader never sees half a file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True, allow_nan=False) + "\n")
        tmp.replace(path)
        return path

    def progress(self, step: int, seconds: float) -> float:
        """How far along the run is, in [0, 1]: the larger of its step and time fractions."""
        parts = []
        if self.steps is not None:
            parts.append(step / self.steps)
        if self.minutes is not None:
            parts.append(seconds / (60.0 * self.minutes))
        return min(1.0, max(parts))

    def learning_rate(self, progress: float) -> float:
        """The scheduled learning rate at `progress` in [0, 1]."""
        p = min(1.0, max(0.0, progress))
        a, b = self.lr_start, self.lr_end
        if self.schedule == "exponential":
            return float(math.exp(math.log(a) + p * (math.log(b) - math.log(a))))
        if self.schedule == "cosine":
            return b + 0.5 * (a - b) * (1.0 + math.cos(math.pi * p))
        if self.schedule == "linear":
            return a + p * (b - a)
        return a


def load_config(path: str | Path) -> TrainConfig:
    """Read a configuration written by `TrainConfig.save` (or by hand)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path} is not valid JSON: {exc}") from None
    try:
        return TrainConfig.from_dict(data)
    except (ConfigError, TypeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None


def key_values(items: list[str], flag: str) -> dict[str, Any]:
    """KEY=VALUE command-line items as a dict, each value read as JSON where it is JSON
    (numbers, lists, true/false) and as text otherwise."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"{flag} must be KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(text)
        except json.JSONDecodeError:
            out[key] = text
    return out
