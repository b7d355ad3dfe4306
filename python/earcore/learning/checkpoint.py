"""Checkpoints that resume the same run: the model, the optimiser, the loss combiner,
the step, the training time spent and every random generator's state, written to a
temporary and renamed (an interrupted write leaves the previous checkpoint)."""

from __future__ import annotations

import os
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from earcore.errors import EarcoreError

__all__ = ["CHECKPOINT_NAME", "Checkpoint", "CheckpointError", "find_checkpoint", "load_checkpoint", "rng_state", "save_checkpoint", "set_rng_state"]

CHECKPOINT_NAME = "checkpoint.pt"


class CheckpointError(EarcoreError, ValueError):
    """A checkpoint that is missing, unreadable or does not fit the model it is loaded into."""


@dataclass
class Checkpoint:
    step: int
    seconds: float
    model: dict[str, Any]
    optimiser: dict[str, Any] | None = None
    combiner: dict[str, Any] | None = None
    rng: dict[str, Any] | None = None
    config: dict[str, Any] | None = None
    #: what the network needs to be rebuilt (its name and options, robots, keypoint names, ...)
    meta: dict[str, Any] = field(default_factory=dict)
    #: the early stop's state: the best watched value and the evaluations since it
    patience: dict[str, float] | None = None


def rng_state() -> dict[str, Any]:
    state: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | Path, checkpoint: Checkpoint) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(checkpoint.__dict__, tmp)
    tmp.replace(path)
    return path


def find_checkpoint(path: str | Path) -> Path:
    """`path` itself if a file, else the run folder's checkpoint."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    return path


def load_checkpoint(path: str | Path) -> Checkpoint:
    path = find_checkpoint(path)
    try:
        # The optimiser's and generators' states hold numpy arrays and tuples, so the full unpickler is needed;
        # checkpoints are files this package wrote.
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises RuntimeError, pickle errors, EOFError for damaged files
        raise CheckpointError(f"{path} is not a readable checkpoint: {type(exc).__name__}: {exc}") from None
    if not isinstance(data, dict) or "model" not in data or "step" not in data:
        raise CheckpointError(f"{path} is not an earcore checkpoint (no model state or step)")
    known = set(Checkpoint.__dataclass_fields__)
    return Checkpoint(**{k: v for k, v in data.items() if k in known})
