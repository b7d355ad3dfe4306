"""The parts detector of the IROS 2018 paper: a fully convolutional encoder-decoder on
RGB-D with one output channel per part type, whose activations (sigmoid, in [0, 1])
are the part's segmentation and whose activation-weighted centroid is its pickup point.

The paper's layer list (Fig. 3) is lost; its predecessor (the Year-Two report's Table
2.2: convolutions with 2×2 average pooling down to a class vector, transposed
convolutions back up, ReLU, 15 % dropout in the innermost layers) is what "paper"
builds, without the 4,096-wide innermost layers. "small" (the default, for CPUs) is
narrower and adds FCN-style skip connections, which keep the activations sharp at a
fraction of the steps; leaky ReLUs throughout (the paper's own fix for the dying units
it saw).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn

from earcore.errors import ConfigError

__all__ = ["PRESETS", "DetectorOptions", "PartDetector", "build_detector"]


@dataclass(frozen=True)
class DetectorOptions:
    classes: int = 13
    in_channels: int = 4
    width: int = 128
    height: int = 96
    #: Channels of each encoder stage; each stage halves the image.
    widths: tuple[int, ...] = (16, 32, 64, 96)
    skips: bool = True
    dropout: float = 0.15
    leak: float = 0.02

    def validate(self) -> DetectorOptions:
        if self.classes < 1 or self.in_channels < 1 or not self.widths or min(self.widths) < 1:
            raise ConfigError(f"detector: classes, in_channels and widths must be positive, got {self}")
        step = 2 ** len(self.widths)
        if self.width % step or self.height % step:
            raise ConfigError(f"detector: with {len(self.widths)} stages the image size must be a multiple of {step}, got {self.width}x{self.height}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"detector: dropout must be in [0, 1), got {self.dropout}")
        return self

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d


PRESETS: dict[str, dict[str, Any]] = {
    "small": {"widths": (16, 32, 64, 96), "skips": True},
    "paper": {"widths": (64, 128, 256, 512, 512), "skips": False},
}


def _block(cin: int, cout: int, leak: float) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.LeakyReLU(leak),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.LeakyReLU(leak),
    )


class PartDetector(nn.Module):
    """(B, in_channels, H, W) → {"logits", "activations"}: (B, classes, H, W)."""

    def __init__(self, options: DetectorOptions) -> None:
        super().__init__()
        self.options = o = options.validate()
        self.encoder = nn.ModuleList()
        cin = o.in_channels
        for w in o.widths:
            self.encoder.append(_block(cin, w, o.leak))
            cin = w
        self.pool = nn.AvgPool2d(2)
        self.bottleneck = nn.Sequential(_block(cin, cin, o.leak), nn.Dropout2d(o.dropout))
        self.up = nn.ModuleList()
        self.decoder = nn.ModuleList()
        for w in reversed(o.widths):
            self.up.append(nn.ConvTranspose2d(cin, w, 2, stride=2))
            self.decoder.append(_block(w * (2 if o.skips else 1), w, o.leak))
            cin = w
        self.head = nn.Conv2d(cin, o.classes, 1)
        assert self.head.bias is not None
        nn.init.constant_(self.head.bias, -4.6)  # start near 1 % activation: soft IoU then sees its background

    def forward(self, image: Tensor) -> dict[str, Tensor]:
        x = image
        skips = []
        for i, block in enumerate(self.encoder):
            x = block(x)
            if i >= len(self.encoder) - 2 and self.options.dropout > 0:  # the innermost stages, as the paper
                x = nn.functional.dropout2d(x, self.options.dropout, self.training)
            skips.append(x)
            x = self.pool(x)
        x = self.bottleneck(x)
        for up, block, skip in zip(self.up, self.decoder, reversed(skips)):
            x = up(x)
            x = block(torch.cat([x, skip], 1) if self.options.skips else x)
        logits = self.head(x)
        return {"logits": logits, "activations": torch.sigmoid(logits)}


def build_detector(classes: int, width: int, height: int, preset: str = "small", **options: Any) -> PartDetector:
    if preset not in PRESETS:
        raise ConfigError(f"unknown detector preset {preset!r}; known: {', '.join(PRESETS)}")
    settings = {**PRESETS[preset], **options}
    if "widths" in settings:
        settings["widths"] = tuple(int(w) for w in settings["widths"])
    unknown = sorted(set(settings) - set(DetectorOptions.__dataclass_fields__))
    if unknown:
        raise ConfigError(f"unknown detector option(s) {', '.join(unknown)}; known: {', '.join(DetectorOptions.__dataclass_fields__)}")
    return PartDetector(DetectorOptions(classes=classes, width=width, height=height, **settings))
