"""How well a parts detector finds pickup points, in the IROS 2018 paper's terms.

* During training (`evaluator`): per part, the centroid of its class's activations in
  its Voronoi cell (the training loss's reading, labels telling where the parts are);
  the IoU error, the distance in px and cm, the pickup error (Eq. 4) and the paper's
  combined error (pickup error + IoU error, Figs. 10 and 13).
* After training (`evaluate`): the picks a robot would make (`earcore.parts.pickup`:
  k-means with each class's count known), matched to the parts of their class; per
  class and overall: the pickup rate (1 − Eq. 4), the median distance (cm) and the IoU
  of the thresholded activations (> 0.5).

A distance in pixels becomes cm in the plane through the part's pickup point parallel
to the image: z·√((Δu/fx)² + (Δv/fy)²).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from earcore.learning.losses import part_centroids, pickup_error, soft_iou_error
from earcore.learning.train import collate, to_device
from earcore.parts.pickup import pickup_points

__all__ = ["ClassRow", "PartsEvaluation", "evaluate", "evaluator", "metric_cm"]


def metric_cm(du: np.ndarray | torch.Tensor, dv: np.ndarray | torch.Tensor, z, fx, fy):
    """Pixel offsets → cm at depth z (m) for focal lengths fx, fy (px)."""
    lib: Any = torch if isinstance(du, torch.Tensor) else np
    return 100.0 * z * lib.sqrt((du / fx) ** 2 + (dv / fy) ** 2)


def evaluator(batch_size: int = 32):
    """The periodic evaluation for `earcore.learning.train.train`."""

    def run(model: torch.nn.Module, dataset: Any, device: torch.device, limit: int | None) -> dict[str, float]:
        n = len(dataset) if limit is None else min(limit, len(dataset))
        iou, px, cm = [], [], []
        with torch.no_grad():
            for start in range(0, n, batch_size):
                batch = to_device(collate([dataset[i] for i in range(start, min(n, start + batch_size))]), device)
                a = model(batch["image"])["activations"]
                iou.append(float(soft_iou_error(a, batch["target"])) * a.shape[0])
                centre = part_centroids(a, batch["points"], batch["classes"], batch["valid"])
                d = centre - batch["points"]
                k = batch["intrinsics"]
                dist_cm = metric_cm(d[..., 0], d[..., 1], batch["depth"], k[:, None, 0], k[:, None, 1])
                px.append(torch.sqrt((d**2).sum(-1))[batch["valid"]].cpu())
                cm.append(dist_cm[batch["valid"]].cpu())
        d_px, d_cm = torch.cat(px), torch.cat(cm)
        iou_error = float(np.sum(iou)) / max(n, 1)
        pick = float(pickup_error(d_cm).mean()) if len(d_cm) else float("nan")
        return {
            "val_iou_error": iou_error,
            "val_distance_px": float(d_px.mean()) if len(d_px) else float("nan"),
            "val_distance_cm": float(d_cm.median()) if len(d_cm) else float("nan"),
            "val_pickup_error": pick,
            "val_combined": pick + iou_error,
        }

    return run


@dataclass
class ClassRow:
    name: str
    parts: int = 0
    pickup_rates: list[float] = field(default_factory=list)
    distances_cm: list[float] = field(default_factory=list)
    intersection: int = 0
    union: int = 0

    @property
    def pickup_rate(self) -> float:
        return float(np.mean(self.pickup_rates)) if self.pickup_rates else float("nan")

    @property
    def median_cm(self) -> float:
        return float(np.median(self.distances_cm)) if self.distances_cm else float("nan")

    @property
    def iou(self) -> float:
        return self.intersection / self.union if self.union else float("nan")


@dataclass
class PartsEvaluation:
    rows: list[ClassRow]
    images: int

    @property
    def overall(self) -> ClassRow:
        total = ClassRow("all")
        for r in self.rows:
            total.parts += r.parts
            total.pickup_rates += r.pickup_rates
            total.distances_cm += r.distances_cm
            total.intersection += r.intersection
            total.union += r.union
        return total

    def to_dict(self) -> dict[str, Any]:
        def row(r: ClassRow) -> dict[str, Any]:
            return {"parts": r.parts, "pickup_rate": r.pickup_rate, "median_cm": r.median_cm, "iou": r.iou}

        return {"images": self.images, "classes": {r.name: row(r) for r in self.rows}, "all": row(self.overall)}

    def markdown(self) -> str:
        lines = [
            f"Pickup points on {self.images} test images (k-means with each class's count known):",
            "",
            "| part | parts | pickup rate | median distance (cm) | IoU |",
            "|---|---|---|---|---|",
        ]
        for r in [*self.rows, self.overall]:
            name = f"**{r.name}**" if r.name == "all" else r.name
            lines.append(f"| {name} | {r.parts} | {100 * r.pickup_rate:.1f} % | {r.median_cm:.2f} | {100 * r.iou:.1f} % |")
        return "\n".join(lines) + "\n"


def _match(predicted: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Index of the prediction for each true point minimising the summed distance
    (exhaustive up to 7 parts of a class, greedy beyond)."""
    k = len(truth)
    cost = np.linalg.norm(truth[:, None] - predicted[None], axis=-1)
    cost = np.where(np.isfinite(cost), cost, 1e9)
    if k <= 7:
        best = min(itertools.permutations(range(len(predicted)), k), key=lambda p: cost[np.arange(k), list(p)].sum())
        return np.array(best)
    out = np.full(k, -1)
    free = set(range(len(predicted)))
    for t, p in sorted(((t, p) for t in range(k) for p in range(len(predicted))), key=lambda tp: cost[tp]):
        if out[t] < 0 and p in free:
            out[t] = p
            free.discard(p)
    return out


def evaluate(
    model: torch.nn.Module, dataset: Any, classes: list[str], device: torch.device | str = "cpu", batch_size: int = 32, limit: int | None = None
) -> PartsEvaluation:
    """Pickup rate, distance and IoU per class over `dataset` (see the module doc)."""
    device = torch.device(device)
    rows = [ClassRow(c) for c in classes]
    n = len(dataset) if limit is None else min(limit, len(dataset))
    model.eval()
    with torch.no_grad():
        for start in range(0, n, batch_size):
            batch = collate([dataset[i] for i in range(start, min(n, start + batch_size))])
            a = model(batch["image"].to(device))["activations"].cpu().numpy()
            for i in range(a.shape[0]):
                valid = batch["valid"][i].numpy()
                cls = batch["classes"][i].numpy()[valid]
                points = batch["points"][i].numpy()[valid]
                z = batch["depth"][i].numpy()[valid]
                fx, fy = (float(v) for v in batch["intrinsics"][i][:2])
                picks = pickup_points(a[i], batch["counts"][i].numpy())
                target = batch["target"][i].numpy() > 0.5
                found = a[i] > 0.5
                for c, row in enumerate(rows):
                    row.intersection += int((found[c] & target[c]).sum())
                    row.union += int((found[c] | target[c]).sum())
                    mine = np.flatnonzero(cls == c)
                    if not len(mine):
                        continue
                    guesses = np.array([[p.u, p.v] for p in picks if p.cls == c])
                    order = _match(guesses, points[mine])
                    d = guesses[order] - points[mine]
                    cm = np.nan_to_num(metric_cm(d[:, 0], d[:, 1], z[mine], fx, fy), nan=1e3)
                    row.parts += len(mine)
                    row.distances_cm += cm.tolist()
                    row.pickup_rates += (1.0 - cm**2 / (cm**2 + 1.0)).tolist()
    return PartsEvaluation(rows, n)
