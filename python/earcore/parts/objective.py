"""The detector's losses (IROS 2018): soft IoU error and the pickup point's centroid
distance, named "iou" and "distance" for the loss combiners."""

from __future__ import annotations

from collections.abc import Mapping

from torch import Tensor

from earcore.learning.losses import centroid_distance, soft_iou_error

__all__ = ["LOSSES", "DetectorObjective"]

LOSSES = ("iou", "distance")


class DetectorObjective:
    """`distance_unit` pixels count as 1 in the distance loss (the paper: raw pixels for
    the sum, KGC/Mean and AuxNet; /100 for KGC, whose weights assume losses in [0, 1])."""

    def __init__(self, distance_unit: float = 1.0) -> None:
        if not distance_unit > 0:
            raise ValueError(f"distance_unit must be positive, got {distance_unit}")
        self.distance_unit = float(distance_unit)

    def inputs(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, ...]:
        return (batch["image"],)

    def losses(self, batch: Mapping[str, Tensor], outputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        a = outputs["activations"]
        return {
            "iou": soft_iou_error(a, batch["target"]),
            "distance": centroid_distance(a, batch["points"], batch["classes"], batch["valid"]) / self.distance_unit,
        }
