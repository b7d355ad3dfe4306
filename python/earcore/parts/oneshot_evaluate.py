"""How well a one-shot segmenter finds unseen part types, in the AAMAS 2019 paper's
terms, over `earcore.parts.oneshot_data.HeldOutTrials`:

* classification: a trial is correct when the thresholded belief (> 0.5) has a higher
  IoU with the needle type's mask than with any other type's mask in the haystack;
  accuracy over the trials, precision and recall per held-out type;
* IoU of the thresholded belief with the needle type's mask;
* pickup rate for the correctly identified parts: 1 − Eq. 4's pickup error of each
  target part's activation centroid (in its Voronoi cell among the type's parts), in cm
  in the plane of its pickup point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from earcore.learning.losses import part_centroids, pickup_error
from earcore.learning.train import collate, to_device
from earcore.parts.evaluate import metric_cm

__all__ = ["OneShotEvaluation", "TrialResults", "evaluate", "evaluator", "score_trials"]


@dataclass
class TrialResults:
    """Per trial: the needle's type, the type the prediction matched best (-1: none),
    the IoU with the needle type's mask; per target part of a correct trial its pickup
    error."""

    cls: list[int] = field(default_factory=list)
    chosen: list[int] = field(default_factory=list)
    iou: list[float] = field(default_factory=list)
    pickup_errors: list[float] = field(default_factory=list)

    def add(self, other: TrialResults) -> None:
        self.cls += other.cls
        self.chosen += other.chosen
        self.iou += other.iou
        self.pickup_errors += other.pickup_errors

    @property
    def accuracy(self) -> float:
        return float(np.mean(np.array(self.cls) == np.array(self.chosen))) if self.cls else float("nan")

    @property
    def mean_iou(self) -> float:
        return float(np.mean(self.iou)) if self.iou else float("nan")

    @property
    def pickup_rate(self) -> float:
        return 1.0 - float(np.mean(self.pickup_errors)) if self.pickup_errors else float("nan")


def score_trials(belief: torch.Tensor, batch: dict[str, torch.Tensor]) -> TrialResults:
    """Score a batch of trials from the segmenter's belief (B, 1, H, W)."""
    found = belief[:, 0] > 0.5  # (B, H, W)
    masks = batch["masks"] > 0.5  # (B, C, H, W)
    present = masks.flatten(2).any(2)
    inter = (found[:, None] & masks).flatten(2).sum(2).float()
    union = (found[:, None] | masks).flatten(2).sum(2).float()
    iou = torch.where(present, inter / union.clamp(min=1), torch.full_like(inter, -1.0))
    best = iou.argmax(1)
    best_iou = iou.gather(1, best[:, None])[:, 0]
    cls = batch["cls"]
    chosen = torch.where(best_iou > 0, best, torch.full_like(best, -1))
    # a tie with another present type is not a win
    ties = ((iou == best_iou[:, None]) & present).sum(1) > 1
    chosen = torch.where(ties, torch.full_like(chosen, -1), chosen)
    target_iou = iou.gather(1, cls[:, None])[:, 0]
    out = TrialResults(cls.tolist(), chosen.tolist(), target_iou.tolist())
    correct = chosen == cls
    if bool(correct.any()):
        valid = batch["valid"] & correct[:, None]
        centre = part_centroids(belief, batch["points"], torch.zeros_like(batch["valid"], dtype=torch.long), valid)
        d = centre - batch["points"]
        k = batch["intrinsics"]
        cm = metric_cm(d[..., 0], d[..., 1], batch["depth"], k[:, None, 0], k[:, None, 1])
        out.pickup_errors = pickup_error(cm[valid]).tolist()
    return out


def _run(model: Any, dataset: Any, device: torch.device, limit: int | None, batch_size: int) -> tuple[TrialResults, TrialResults]:
    """(the model's results, those of a belief marking every part of the haystack)."""
    n = len(dataset) if limit is None else min(limit, len(dataset))
    results, every_part = TrialResults(), TrialResults()
    was_training = model.training
    model.eval()
    with torch.no_grad():
        for start in range(0, n, batch_size):
            batch = to_device(collate([dataset[i] for i in range(start, min(n, start + batch_size))]), device)
            results.add(score_trials(model.segment(batch["needle"], batch["haystack"], batch["needle_mask"]), batch))
            every_part.add(score_trials(batch["masks"].amax(1, keepdim=True), batch))
    model.train(was_training)
    return results, every_part


def evaluator(batch_size: int = 32):
    """The periodic evaluation for `earcore.learning.train.train` (lower is better:
    val_error = 1 − accuracy)."""

    def run(model: torch.nn.Module, dataset: Any, device: torch.device, limit: int | None) -> dict[str, float]:
        r, _ = _run(model, dataset, device, limit, batch_size)
        return {"val_error": 1.0 - r.accuracy, "val_accuracy": r.accuracy, "val_iou": r.mean_iou, "val_pickup_rate": r.pickup_rate}

    return run


@dataclass
class OneShotEvaluation:
    classes: list[str]
    held_out: list[int]
    results: TrialResults
    #: a belief marking every part in the haystack: the score of ignoring the needle
    #: (above 1 / types, since the metric favours the larger parts' masks)
    every_part: TrialResults
    #: what the trials' types are, for the report
    kind: str = "held-out"

    def per_class(self) -> dict[str, dict[str, float]]:
        cls, chosen = np.array(self.results.cls), np.array(self.results.chosen)
        out = {}
        for c in self.held_out:
            picked = chosen == c
            out[self.classes[c]] = {
                "trials": int((cls == c).sum()),
                "recall": float(np.mean(chosen[cls == c] == c)) if (cls == c).any() else float("nan"),
                "precision": float(np.mean(cls[picked] == c)) if picked.any() else float("nan"),
            }
        return out

    def to_dict(self) -> dict[str, Any]:
        r = self.results
        return {
            "trials": len(r.cls),
            "accuracy": r.accuracy,
            "iou": r.mean_iou,
            "pickup_rate": r.pickup_rate,
            "every_part_accuracy": self.every_part.accuracy,
            "classes": self.per_class(),
        }

    def markdown(self) -> str:
        r = self.results
        lines = [
            f"{len(r.cls)} trials on {self.kind} types; accuracy {100 * r.accuracy:.1f} %, IoU {r.mean_iou:.3f}, "
            f"pickup rate (correct trials) {100 * r.pickup_rate:.1f} %; marking every part instead would score {100 * self.every_part.accuracy:.1f} %",
            "",
            f"| {self.kind.capitalize()} type | Trials | Precision | Recall |",
            "|---|---|---|---|",
        ]
        for name, row in self.per_class().items():
            lines.append(f"| {name} | {row['trials']} | {row['precision']:.2f} | {row['recall']:.2f} |")
        return "\n".join(lines) + "\n"


def evaluate(model: Any, trials: Any, device: torch.device | str = "cpu", batch_size: int = 32, kind: str = "held-out") -> OneShotEvaluation:
    """The trials' results; `kind` names their types in the report ("held-out", "trained")."""
    results, every_part = _run(model, trials, torch.device(device), None, batch_size)
    return OneShotEvaluation(list(trials.haystacks.classes), list(trials.held_out), results, every_part, kind)
