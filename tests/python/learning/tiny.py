"""A tiny regression task for the training loop's tests: samples with an "image" and a
3D target; the model maps the flattened image to (N, 2, 3) keypoints."""

from __future__ import annotations

import torch

from earcore.learning.losses import joint_loss


class TinySet(torch.utils.data.Dataset):
    def __init__(self, count: int = 24, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        self.x = torch.rand(count, 3, 4, 4, generator=g)
        self.y = torch.randn(count, 2, 3, generator=g)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        # per-epoch noise, as the image Dataset adds
        g = torch.Generator().manual_seed(1000 * self.epoch + i)
        return {"image": self.x[i] + 0.01 * torch.randn(self.x[i].shape, generator=g), "keypoints": self.y[i], "keypoint_valid": torch.ones(2, dtype=torch.bool)}


class TinyNet(torch.nn.Module):
    def __init__(self, dropout: float = 0.2):
        super().__init__()
        self.body = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(48, 16), torch.nn.ReLU(), torch.nn.Dropout(dropout), torch.nn.Linear(16, 6))

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"keypoints": self.body(image).view(-1, 2, 3)}


class TinyObjective:
    def __init__(self, interrupt_at: int | None = None):
        self.calls, self.interrupt_at = 0, interrupt_at

    def inputs(self, batch):
        self.calls += 1
        if self.interrupt_at is not None and self.calls == self.interrupt_at:
            raise KeyboardInterrupt
        return (batch["image"],)

    def losses(self, batch, outputs):
        return {"joints": joint_loss(outputs["keypoints"], batch["keypoints"], batch["keypoint_valid"])}
