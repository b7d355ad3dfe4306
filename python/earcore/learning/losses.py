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

The parts detector's (IROS 2018, §V):

- `soft_iou_error`: 1 − the differentiable IoU of activations a in [0, 1] and a 0/1
  target g, ``Σ a·g / Σ (a + g − a·g)`` per image over every class channel and pixel
  (activations on a class the image lacks count against it), batch mean.
- `centroid_distance`: the distance (pixels) of the activation-weighted centroid to the
  pickup point. The paper's definition takes a class channel's whole image; with several
  parts of one class each part gets the pixels nearer to its pickup point than to the
  others' of its class (its Voronoi cell), which is the paper's where a class appears
  once. Mean over the batch's parts.
- `pickup_error` (Eq. 4): ``d² / (d² + 1)`` of a distance d in cm: 0.5 at 1 cm.

The one-shot segmenter's (AAMAS 2019, Eqs. 1-2):

- `vector_spread`: over every pair (i, j) of a batch's two sets of feature vectors, the
  angle between X_i and Y_j in units of π/2 (so orthogonal is 1), counted as is where
  the classes agree and as 1 − it where they differ; the mean over the b×b pairs. 0 when
  each class has its own direction, orthogonal to every other class's.

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
    "centroid_distance",
    "mask_loss",
    "part_centroids",
    "pickup_error",
    "soft_iou_error",
    "type_loss",
    "vector_spread",
    "voronoi_cells",
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


def soft_iou_error(activations: Tensor, target: Tensor) -> Tensor:
    """1 − soft IoU per image over channels and pixels, batch mean; `activations` in
    [0, 1] and `target` (0/1) of the same shape (B, C, H, W). An image whose target and
    activations are both empty has IoU 1."""
    if activations.shape != target.shape:
        raise ValueError(f"activations {tuple(activations.shape)} and target {tuple(target.shape)} differ in shape")
    a, g = activations.flatten(1), target.flatten(1).to(activations.dtype)
    inter = (a * g).sum(1)
    union = (a + g - a * g).sum(1)
    iou = torch.where(union > 0, inter / union.clamp(min=1e-12), torch.ones_like(union))
    return (1.0 - iou).mean()


def voronoi_cells(points: Tensor, classes: Tensor, valid: Tensor, height: int, width: int) -> Tensor:
    """(B, M, H, W) 0/1: pixel (row v, column u) belongs to part m when m is valid and
    no valid part of its class in the image has its point (u, v) nearer (ties: both)."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=points.dtype, device=points.device), torch.arange(width, dtype=points.dtype, device=points.device), indexing="ij"
    )
    pixels = torch.stack([u, v], dim=-1).reshape(1, 1, -1, 2)
    d2 = ((pixels - points[:, :, None, :]) ** 2).sum(-1)  # (B, M, HW)
    same = (classes[:, :, None] == classes[:, None, :]) & valid[:, None, :] & valid[:, :, None]  # (B, M, M)
    inf = torch.tensor(float("inf"), dtype=d2.dtype, device=d2.device)
    rivals = torch.full_like(d2, float("inf"))  # distance to the nearest valid same-class point, self included
    for k in range(points.shape[1]):
        rivals = torch.minimum(rivals, torch.where(same[:, :, k, None], d2[:, k, None, :], inf))
    cells = (d2 <= rivals) & valid[:, :, None]
    return cells.reshape(*points.shape[:2], height, width).to(points.dtype)


def part_centroids(activations: Tensor, points: Tensor, classes: Tensor, valid: Tensor, eps: float = 1e-6) -> Tensor:
    """(B, M, 2) activation-weighted centroid (u, v) of each part's class channel within
    its Voronoi cell (`voronoi_cells`); `activations` (B, C, H, W) >= 0, `points` (B, M, 2)
    (u, v) px, `classes` (B, M) long, `valid` (B, M) bool. A cell without activation
    gives (0, 0)."""
    _, _, h, w = activations.shape
    with torch.no_grad():
        cells = voronoi_cells(points, classes, valid, h, w)
    channel = torch.gather(activations, 1, classes.clamp(min=0)[:, :, None, None].expand(-1, -1, h, w))  # (B, M, H, W)
    weight = channel * cells
    v, u = torch.meshgrid(
        torch.arange(h, dtype=activations.dtype, device=activations.device), torch.arange(w, dtype=activations.dtype, device=activations.device), indexing="ij"
    )
    mass = weight.sum((2, 3)) + eps
    return torch.stack([(weight * u).sum((2, 3)) / mass, (weight * v).sum((2, 3)) / mass], dim=-1)


def centroid_distance(activations: Tensor, points: Tensor, classes: Tensor, valid: Tensor) -> Tensor:
    """Mean over the valid parts of the distance (pixels) from `part_centroids` to the
    part's point. With no valid part: 0 (no gradient)."""
    if not bool(valid.any()):
        return activations.sum() * 0.0
    centroid = part_centroids(activations, points, classes, valid)
    distance = torch.sqrt(((centroid - points) ** 2).sum(-1) + _TINY)
    return distance[valid].mean()


def pickup_error(distance_cm: Tensor) -> Tensor:
    """Eq. 4 of the IROS 2018 paper: the chance a grasp at this distance (cm) from the
    pickup point fails, d² / (d² + 1)."""
    d2 = distance_cm**2
    return d2 / (d2 + 1.0)


def vector_spread(x: Tensor, y: Tensor, same: Tensor) -> Tensor:
    """The vector-spread loss of `x` (B, D) against `y` (B', D) with `same` (B, B') True
    where the classes of x_i and y_j agree. Angles use cos clamped inside (-1, 1), whose
    arccos has a finite gradient; a zero vector counts as orthogonal to everything."""
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1] or same.shape != (x.shape[0], y.shape[0]):
        raise ValueError(f"vector_spread takes x (B, D), y (B', D) and same (B, B'), got {tuple(x.shape)}, {tuple(y.shape)}, {tuple(same.shape)}")
    cos = F.normalize(x, dim=1, eps=1e-12) @ F.normalize(y, dim=1, eps=1e-12).T
    angle = torch.arccos(cos.clamp(-1.0 + 1e-6, 1.0 - 1e-6)) / (math.pi / 2)
    return torch.where(same, angle, 1.0 - angle).mean()
