"""Per network: which inputs the model gets in training and which named losses a batch
gives (`earcore.learning.losses`), with the loss weights it trains with by default.

Batches are the Dataset's dicts of tensors ("image", "mask", "keypoints",
"keypoint_valid", "pixels", "base", "robot", "intrinsics", ...)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from earcore.errors import ConfigError
from earcore.learning.losses import PAPER_V_WEIGHTS, base_loss, joint_loss, mask_loss, type_loss

__all__ = ["CascadeObjective", "KeypointObjective", "MultiObjective", "default_weights", "objective_for"]


class MultiObjective:
    """Paper V's four objectives: mask (Eqs. 1-4), joints (Eq. 5), base (Eq. 6), type (Eq. 7)."""

    def inputs(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, ...]:
        return (batch["image"],)

    def losses(self, batch: Mapping[str, Tensor], outputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        out = {
            "mask": mask_loss(outputs["mask_logits"], batch["mask"]),
            "joints": joint_loss(outputs["keypoints"], batch["keypoints"], batch["keypoint_valid"]),
            "base": base_loss(outputs["base"], batch["base"]),
        }
        if "type_logits" in outputs:
            out["type"] = type_loss(outputs["type_logits"], batch["robot"])
        return out


class CascadeObjective(MultiObjective):
    """Paper IV: the mask CNN's loss and the joint CNN's, the latter fed the ground-truth
    mask with probability `teacher` per batch (the paper trained it on ground-truth
    masks: 1.0) and the mask CNN's own otherwise. No type head."""

    def __init__(self, teacher: float = 1.0, seed: int = 0):
        if not 0.0 <= teacher <= 1.0:
            raise ConfigError(f"teacher must be in [0, 1], got {teacher!r}")
        self.teacher = teacher
        self.generator = torch.Generator().manual_seed(seed)

    def inputs(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, ...]:
        if self.teacher >= 1.0 or float(torch.rand((), generator=self.generator)) < self.teacher:
            return (batch["image"], batch["mask"])
        return (batch["image"],)


def _in_image(pixels: Tensor, size: tuple[int, int]) -> Tensor:
    w, h = size
    return (pixels[..., 0] >= -0.5) & (pixels[..., 0] <= w - 0.5) & (pixels[..., 1] >= -0.5) & (pixels[..., 1] <= h - 0.5)


class KeypointObjective(MultiObjective):
    """The keypoint variant: Paper V's four losses on its back-projected outputs, plus
    "pixels" (mean 2D distance over in-image keypoints and base, in units of a tenth of
    the image width) and "depth" (mean |log z - log z_true|), which give the heatmaps
    and the depth maps direct signals. The images' own intrinsics are used."""

    def inputs(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, ...]:
        return (batch["image"], None, batch["intrinsics"])  # type: ignore[return-value]

    def losses(self, batch: Mapping[str, Tensor], outputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        out = super().losses(batch, outputs)
        k = batch["intrinsics"]
        base = batch["base"]
        z_base = base[:, 2].clamp(min=1e-3)
        base_px = torch.stack([k[:, 0, 0] * base[:, 0] / z_base + k[:, 0, 2], k[:, 1, 1] * base[:, 1] / z_base + k[:, 1, 2]], 1)
        target = torch.cat([batch["pixels"], base_px[:, None]], 1)
        points = torch.cat([batch["keypoints"], base[:, None]], 1)
        valid = torch.cat([batch["keypoint_valid"], torch.ones_like(batch["keypoint_valid"][:, :1])], 1) & (points[..., 2] > 1e-3)
        size = (batch["image"].shape[3], batch["image"].shape[2])
        seen = (valid & _in_image(target, size)).to(target.dtype)
        distance = torch.sqrt(((outputs["pixels"] - target) ** 2).sum(-1) + 1e-12) / (0.1 * size[0])
        out["pixels"] = (distance * seen).sum() / seen.sum().clamp(min=1.0)
        predicted_z = torch.cat([outputs["keypoints"][..., 2], outputs["base"][:, None, 2]], 1).clamp(min=1e-3)
        log_error = (predicted_z.log() - points[..., 2].clamp(min=1e-3).log()).abs()
        v = valid.to(log_error.dtype)
        out["depth"] = (log_error * v).sum() / v.sum().clamp(min=1.0)
        return out


def default_weights(network: str) -> dict[str, float]:
    """Paper V's weights (mask 1.0, joints 1.5, base 1.5, type 0.3); the cascade's two
    CNNs are independent (detached), so its weights only scale each one's learning rate
    under SGD (1 each); the keypoint variant adds pixels 1.0 and depth 1.0."""
    if network == "cascade":
        return {"mask": 1.0, "joints": 1.0, "base": 1.0}
    if network == "keypoint":
        return {**PAPER_V_WEIGHTS, "pixels": 1.0, "depth": 1.0}
    return dict(PAPER_V_WEIGHTS)


def objective_for(network: str, *, teacher: float = 1.0, seed: int = 0) -> MultiObjective:
    if network == "multi":
        return MultiObjective()
    if network == "cascade":
        return CascadeObjective(teacher, seed)
    if network == "keypoint":
        return KeypointObjective()
    raise ConfigError(f"network must be one of multi, cascade, keypoint, got {network!r}")
