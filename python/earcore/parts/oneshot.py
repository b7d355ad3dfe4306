"""The one-shot segmenter of the AAMAS 2019 paper: a fully convolutional Siamese network
whose filters are gated by the needle.

The needle (one image of the wanted part) and the haystack pass through the same
convolution stacks. The needle's pass gives one weight per filter: the filter's mean
positive response over the needle, divided by the mean over its stack (so a stack's
scale is kept). The haystack's pass multiplies every filter's output by its weight, so
filters the needle does not excite are switched off; no difference metric is learned.
Transposed convolutions (FCN-style, with skips from the gated stacks) bring the
haystack back to its size as one belief map. Without a needle (`gates=None`) every
filter stays on: the paper's task 2, all objects.

Outputs of `forward(needle, haystack, second)` (the four tasks; `tasks` picks which
are computed): "needle" (B, 1, H, W) the needle's type in the haystack, "all" every part
in the haystack, "self" the needle re-found in the needle image, "vector" / "second" the
last stack's pooled filter responses of the needle and of a second needle of the same
type (the vector spread's inputs).

GroupNorm, not BatchNorm: needles and haystacks are different statistics, and a
per-sample norm keeps no running average to mix them in.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor, nn

from earcore.errors import ConfigError

__all__ = ["TASKS", "OneShotOptions", "OneShotSegmenter", "build_oneshot"]

TASKS = ("needle", "all", "self", "spread")


@dataclass(frozen=True)
class OneShotOptions:
    in_channels: int = 4
    widths: tuple[int, ...] = (16, 32, 64, 128)
    tasks: tuple[str, ...] = TASKS
    dropout: float = 0.15
    leak: float = 0.02

    def validate(self) -> OneShotOptions:
        if self.in_channels not in (3, 4):
            raise ConfigError(f"one-shot: in_channels is 3 (RGB) or 4 (RGB-D), got {self.in_channels}")
        if not self.widths or min(self.widths) < 4 or any(w % 4 for w in self.widths):
            raise ConfigError(f"one-shot: widths must be positive multiples of 4, got {self.widths}")
        unknown = [t for t in self.tasks if t not in TASKS]
        if unknown or "needle" not in self.tasks:
            raise ConfigError(f"one-shot: tasks must include 'needle' and come from {', '.join(TASKS)}, got {self.tasks}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"one-shot: dropout must be in [0, 1), got {self.dropout}")
        return self

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["widths"], d["tasks"] = list(self.widths), list(self.tasks)
        return d


def _stack(cin: int, cout: int, leak: float) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.GroupNorm(4, cout),
        nn.LeakyReLU(leak),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.GroupNorm(4, cout),
        nn.LeakyReLU(leak),
    )


class OneShotSegmenter(nn.Module):
    def __init__(self, options: OneShotOptions) -> None:
        super().__init__()
        self.options = o = options.validate()
        self.stacks = nn.ModuleList()
        cin = o.in_channels
        for w in o.widths:
            self.stacks.append(_stack(cin, w, o.leak))
            cin = w
        self.pool = nn.MaxPool2d(2)
        self.up = nn.ModuleList()
        self.decoder = nn.ModuleList()
        for w in reversed(o.widths[:-1]):
            self.up.append(nn.ConvTranspose2d(cin, w, 2, stride=2))
            self.decoder.append(_stack(2 * w, w, o.leak))
            cin = w
        self.head = nn.Conv2d(cin, 1, 1)
        assert self.head.bias is not None
        nn.init.constant_(self.head.bias, -2.0)  # start near 12 % belief: the soft IoU sees the background
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_normal_(m.weight, a=o.leak, nonlinearity="leaky_relu")

    @property
    def divisor(self) -> int:
        """Image sides must be multiples of this."""
        return 2 ** (len(self.options.widths) - 1)

    def _check(self, image: Tensor, name: str) -> None:
        if image.ndim != 4 or image.shape[1] != self.options.in_channels:
            raise ValueError(f"{name}: expected (B, {self.options.in_channels}, H, W), got {tuple(image.shape)}")
        if image.shape[2] % self.divisor or image.shape[3] % self.divisor:
            raise ValueError(f"{name}: height and width must be multiples of {self.divisor}, got {tuple(image.shape[2:])}")

    def encode(self, image: Tensor, gates: list[Tensor] | None = None) -> list[Tensor]:
        """Each stack's output (before its pooling), multiplied by its gates if given."""
        features = []
        x = image
        for k, stack in enumerate(self.stacks):
            x = stack(x)
            if k >= 2 and self.options.dropout > 0:  # the paper: dropout after stacks 3 on
                x = nn.functional.dropout2d(x, self.options.dropout, self.training)
            if gates is not None:
                x = x * gates[k][:, :, None, None]
            features.append(x)
            if k < len(self.stacks) - 1:
                x = self.pool(x)
        return features

    @staticmethod
    def responses(features: list[Tensor]) -> list[Tensor]:
        """Per stack, each filter's mean positive response (B, filters)."""
        return [f.clamp(min=0).mean((2, 3)) for f in features]

    @staticmethod
    def gates(responses: list[Tensor]) -> list[Tensor]:
        return [r / (r.mean(1, keepdim=True) + 1e-6) for r in responses]

    def decode(self, features: list[Tensor]) -> Tensor:
        x = features[-1]
        for up, block, skip in zip(self.up, self.decoder, reversed(features[:-1])):
            x = block(torch.cat([up(x), skip], 1))
        return self.head(x)

    def needle_gates(self, needle: Tensor) -> tuple[list[Tensor], Tensor]:
        """(gates per stack, the last stack's response vector) of a needle batch."""
        self._check(needle, "needle")
        r = self.responses(self.encode(needle))
        return self.gates(r), r[-1]

    def segment(self, needle: Tensor, haystack: Tensor) -> Tensor:
        """Belief (B, 1, H, W) in [0, 1] that a haystack pixel shows the needle's type."""
        self._check(haystack, "haystack")
        gates, _ = self.needle_gates(needle)
        return torch.sigmoid(self.decode(self.encode(haystack, gates)))

    def forward(self, needle: Tensor, haystack: Tensor, second: Tensor | None = None) -> dict[str, Tensor]:
        self._check(haystack, "haystack")
        gates, vector = self.needle_gates(needle)
        out = {"vector": vector, "needle": torch.sigmoid(self.decode(self.encode(haystack, gates)))}
        tasks = self.options.tasks
        if "all" in tasks:
            out["all"] = torch.sigmoid(self.decode(self.encode(haystack)))
        if "self" in tasks:
            out["self"] = torch.sigmoid(self.decode(self.encode(needle, gates)))
        if "spread" in tasks and second is not None:
            self._check(second, "second")
            out["second"] = self.responses(self.encode(second))[-1]
        return out


def build_oneshot(**options: Any) -> OneShotSegmenter:
    settings = dict(options)
    for key in ("widths", "tasks"):
        if key in settings:
            settings[key] = tuple(settings[key])
    if "widths" in settings:
        settings["widths"] = tuple(int(w) for w in settings["widths"])
    unknown = sorted(set(settings) - set(OneShotOptions.__dataclass_fields__))
    if unknown:
        raise ConfigError(f"unknown one-shot option(s) {', '.join(unknown)}; known: {', '.join(OneShotOptions.__dataclass_fields__)}")
    return OneShotSegmenter(OneShotOptions(**settings))
