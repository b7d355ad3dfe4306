"""The papers' losses (Papers IV, V and VII).

- `mask_loss`: class-weighted binary cross-entropy, Eqs. 1-4 in Paper VII's standard
  form ``l = -w_fg·y·log(p) - w_bg·(1-y)·log(1-p)`` (Papers IV-VI print p and y
  swapped), with ``w_fg = 1/P(fg)`` and ``w_bg = 1/P(bg)``. The papers leave open over
  what P is counted; here it is the ground truth's foreground fraction **per batch**
  (one image's fraction is noisy, a dataset's needs a pass first). p is clipped to
  [eps, 1-eps] (the papers' clip against log 0). Mean over every pixel of the batch
  (Eq. 4: independent of image size).
- `joint_loss` (Eq. 5): per sample, the mean over its valid keypoints of the
  Euclidean distance (not squared), then the mean over the batch.
- `base_loss` (Eq. 6): the Euclidean distance of the base position, batch mean.
- `type_loss` (Eq. 7): categorical cross-entropy, batch mean.

How the named losses become one total (Eq. 8's fixed weights and the learned schemes)
is `earcore.learning.combiners`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "PAPER_V_WEIGHTS",
    "PAPER_VII_WEIGHTS",
    "base_loss",
    "class_weights",
    "joint_loss",
    "mask_loss",
    "type_loss",
]

#: Paper V (and VI): W_mask 1.0, W_Jcoords 1.5, W_Bcoords 1.5, W_type 0.3.
PAPER_V_WEIGHTS = {"mask": 1.0, "joints": 1.5, "base": 1.5, "type": 0.3}
#: Paper VII: 1.2, 1.2, 1.2, 0.6.
PAPER_VII_WEIGHTS = {"mask": 1.2, "joints": 1.2, "base": 1.2, "type": 0.6}

#: Norms get this under the square root so that a perfect prediction has a finite gradient.
_TINY = 1e-12


def class_weights(target: Tensor) -> tuple[Tensor, Tensor]:
    """(w_fg, w_bg) = (1/P(fg), 1/P(bg)) over the whole batch `target` (Eqs. 1-2).
    A batch with no foreground (or no background) pixel counts one, so the weights
    stay finite."""
    n = target.numel()
    if n < 2:
        raise ValueError("class weights need at least two pixels")
    p_fg = target.sum().clamp(1.0, n - 1.0) / n
    return 1.0 / p_fg, 1.0 / (1.0 - p_fg)


def mask_loss(logits: Tensor, target: Tensor, eps: float = 1e-6) -> Tensor:
    """Eqs. 1-4: `logits` and `target` (0/1) of the same shape (N, 1, H, W)."""
    if logits.shape != target.shape:
        raise ValueError(f"mask logits {tuple(logits.shape)} and target {tuple(target.shape)} differ in shape")
    target = target.to(logits.dtype)
    w_fg, w_bg = class_weights(target.detach())
    # log(clip(p, eps, 1-eps)) computed from the logits without forming p.
    lo, hi = math.log(eps), math.log1p(-eps)
    log_p = F.logsigmoid(logits).clamp(lo, hi)
    log_q = F.logsigmoid(-logits).clamp(lo, hi)
    per_pixel = -w_fg * target * log_p - w_bg * (1.0 - target) * log_q
    return per_pixel.mean()


def _distance(a: Tensor, b: Tensor) -> Tensor:
    return torch.sqrt(((a - b) ** 2).sum(-1) + _TINY)


def joint_loss(predicted: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
    """Eq. 5: `predicted`, `target` (N, K, 3); `valid` (N, K) bool (absent keypoints,
    e.g. beyond a 6-joint robot's 7, are left out). Samples with no valid keypoint
    count zero."""
    if predicted.shape != target.shape or predicted.dim() != 3:
        raise ValueError(f"keypoints must both be (N, K, 3), got {tuple(predicted.shape)} and {tuple(target.shape)}")
    d = _distance(predicted, target)
    if valid is None:
        return d.mean()
    if valid.shape != d.shape:
        raise ValueError(f"keypoint_valid must be (N, K) = {tuple(d.shape)}, got {tuple(valid.shape)}")
    w = valid.to(d.dtype)
    per_sample = (d * w).sum(1) / w.sum(1).clamp(min=1.0)
    return per_sample.mean()


def base_loss(predicted: Tensor, target: Tensor) -> Tensor:
    """Eq. 6: `predicted`, `target` (N, 3)."""
    if predicted.shape != target.shape:
        raise ValueError(f"base positions differ in shape: {tuple(predicted.shape)} and {tuple(target.shape)}")
    return _distance(predicted, target).mean()


def type_loss(logits: Tensor, labels: Tensor) -> Tensor:
    """Eq. 7: `logits` (N, R), `labels` (N,) class indices."""
    return F.cross_entropy(logits, labels.long())
