"""The one-shot segmenter of the AAMAS 2019 paper: a fully convolutional Siamese network
whose filters are gated by the needle.

The needle (one image of the wanted part) and the haystack pass through the same
convolution stacks. The needle's pass gives one weight per filter: the filter's mean
positive response over the needle (`pooling="image"`, the paper's) or over the needle's
part pixels only (`pooling="part"`, the default: the platform around the part then
does not dilute the weights), raised to a learned power per stack (`sharpen`: the
network decides how selective the gates are) and divided by the mean over its stack (so
a stack's scale is kept). The haystack's pass multiplies every filter's output by its
weight, so filters the needle does not excite are switched off; no difference metric is
learned. With `match` (the default), the decoder also sees, at every scale, the cosine
similarity of each haystack cell's gated features to the needle's prototype (the mean
of its part's features in the needle's own pass, times the gates): a fixed comparison,
not a learned metric, that tells the decoder directly where the needle's type is.

Transposed convolutions (FCN-style, with skips from the gated stacks) bring the
haystack back to its size as one belief map. Without a needle (`gates=None`) every
filter stays on and the similarity maps are zero: the paper's task 2, all objects.

Outputs of `forward(needle, haystack, second, needle_mask, second_mask)` (the four
tasks; `tasks` picks which are computed): "needle" (B, 1, H, W) the needle's type in the haystack, "all" every part
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

__all__ = ["LEGACY_OPTIONS", "POOLINGS", "TASKS", "OneShotOptions", "OneShotSegmenter", "build_oneshot"]

TASKS = ("needle", "all", "self", "spread")
POOLINGS = ("part", "image")
#: What checkpoints written before these options existed were trained with.
LEGACY_OPTIONS = {"pooling": "image", "sharpen": False, "match": False}


@dataclass(frozen=True)
class OneShotOptions:
    in_channels: int = 4
    widths: tuple[int, ...] = (16, 32, 64, 128)
    tasks: tuple[str, ...] = TASKS
    dropout: float = 0.15
    leak: float = 0.02
    pooling: str = "part"
    sharpen: bool = True
    match: bool = True

    def validate(self) -> OneShotOptions:
        if self.in_channels not in (3, 4):
            raise ConfigError(f"one-shot: in_channels is 3 (RGB) or 4 (RGB-D), got {self.in_channels}")
        if not self.widths or min(self.widths) < 4 or any(w % 4 for w in self.widths):
            raise ConfigError(f"one-shot: widths must be positive multiples of 4, got {self.widths}")
        unknown = [t for t in self.tasks if t not in TASKS]
        if unknown or "needle" not in self.tasks:
            raise ConfigError(f"one-shot: tasks must include 'needle' and come from {', '.join(TASKS)}, got {self.tasks}")
        for name in ("sharpen", "match"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"one-shot: {name} is true or false, got {getattr(self, name)!r}")
        if self.pooling not in POOLINGS:
            raise ConfigError(f"one-shot: pooling is one of {', '.join(POOLINGS)}, got {self.pooling!r}")
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
        extra = 1 if o.match else 0  # the similarity map joins each scale's input
        for w in reversed(o.widths[:-1]):
            self.up.append(nn.ConvTranspose2d(cin + extra, w, 2, stride=2))
            self.decoder.append(_stack(2 * w + extra, w, o.leak))
            cin = w
        self.head = nn.Conv2d(cin, 1, 1)
        # log of each stack's gate power: 0 is the plain ratio to the stack's mean
        self.log_sharpness = nn.Parameter(torch.zeros(len(o.widths)), requires_grad=o.sharpen)
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
    def responses(features: list[Tensor], mask: Tensor | None = None) -> list[Tensor]:
        """Per stack, each filter's mean positive response (B, filters), over the pixels
        of `mask` (B, 1, H, W) when given (weighted by its share of each feature cell)."""
        if mask is None:
            return [f.clamp(min=0).mean((2, 3)) for f in features]
        out = []
        for f in features:
            m = nn.functional.adaptive_avg_pool2d(mask.float(), (f.shape[2], f.shape[3]))
            out.append((f.clamp(min=0) * m).sum((2, 3)) / m.sum((2, 3)).clamp(min=1e-6))
        return out

    def gates(self, responses: list[Tensor]) -> list[Tensor]:
        powers = self.log_sharpness.exp()
        out = []
        for r, p in zip(responses, powers):
            g = (r + 1e-6) ** p
            out.append(g / g.mean(1, keepdim=True))
        return out

    def decode(self, features: list[Tensor], similarity: list[Tensor] | None = None) -> Tensor:
        """The belief's logits from the stacks' outputs and, with `match`, one similarity
        map per stack (zeros without a needle)."""
        if self.options.match and similarity is None:
            similarity = [f.new_zeros(f.shape[0], 1, *f.shape[2:]) for f in features]
        x = features[-1]
        levels = range(len(features) - 2, -1, -1)
        for up, block, k in zip(self.up, self.decoder, levels):
            if similarity is not None:
                x = torch.cat([x, similarity[k + 1]], 1)
            parts = [up(x), features[k]] + ([similarity[k]] if similarity is not None else [])
            x = block(torch.cat(parts, 1))
        return self.head(x)

    @staticmethod
    def similarity(features: list[Tensor], prototypes: list[Tensor]) -> list[Tensor]:
        """Per stack, the cosine similarity (B, 1, h, w) of each cell's features to the
        needle's prototype (B, filters)."""
        return [nn.functional.cosine_similarity(f, p[:, :, None, None], dim=1, eps=1e-6)[:, None] for f, p in zip(features, prototypes)]

    def _find(self, image: Tensor, needle: tuple[list[Tensor], list[Tensor]]) -> Tensor:
        """Belief logits for the needle's type in `image`, given the needle's (gates, prototypes)."""
        gates, prototypes = needle
        features = self.encode(image, gates)
        if not self.options.match:
            return self.decode(features)
        return self.decode(features, self.similarity(features, [p * g for p, g in zip(prototypes, gates)]))

    def _pooling_mask(self, image: Tensor, mask: Tensor | None, name: str) -> Tensor | None:
        if self.options.pooling == "image":
            return None
        if mask is None:
            raise ValueError(f"{name}: this segmenter pools over the part's pixels; give the needle's part mask (parts.oneshot_data.part_mask)")
        if mask.shape != (image.shape[0], 1, *image.shape[2:]):
            raise ValueError(f"{name} mask: expected {(image.shape[0], 1, *image.shape[2:])}, got {tuple(mask.shape)}")
        if bool((mask.flatten(1).sum(1) <= 0).any()):
            raise ValueError(f"{name} mask: a needle's part mask is empty")
        return mask

    def needle_gates(self, needle: Tensor, mask: Tensor | None = None) -> tuple[list[Tensor], Tensor]:
        """(gates per stack, the last stack's response vector) of a needle batch and,
        for `pooling="part"`, its part masks (B, 1, h, w)."""
        (gates, _), vector = self._needle(needle, mask)
        return gates, vector

    def _needle(self, needle: Tensor, mask: Tensor | None) -> tuple[tuple[list[Tensor], list[Tensor]], Tensor]:
        """((gates, prototypes) per stack, the last stack's response vector)."""
        self._check(needle, "needle")
        pooling = self._pooling_mask(needle, mask, "needle")
        features = self.encode(needle)
        r = self.responses(features, pooling)
        prototypes = self.means(features, pooling) if self.options.match else []
        return (self.gates(r), prototypes), r[-1]

    @staticmethod
    def means(features: list[Tensor], mask: Tensor | None) -> list[Tensor]:
        """Per stack, each filter's mean output (B, filters) over `mask`'s pixels (or all)."""
        if mask is None:
            return [f.mean((2, 3)) for f in features]
        out = []
        for f in features:
            m = nn.functional.adaptive_avg_pool2d(mask.float(), (f.shape[2], f.shape[3]))
            out.append((f * m).sum((2, 3)) / m.sum((2, 3)).clamp(min=1e-6))
        return out

    def segment(self, needle: Tensor, haystack: Tensor, needle_mask: Tensor | None = None) -> Tensor:
        """Belief (B, 1, H, W) in [0, 1] that a haystack pixel shows the needle's type."""
        self._check(haystack, "haystack")
        found, _ = self._needle(needle, needle_mask)
        return torch.sigmoid(self._find(haystack, found))

    def forward(
        self, needle: Tensor, haystack: Tensor, second: Tensor | None = None, needle_mask: Tensor | None = None, second_mask: Tensor | None = None
    ) -> dict[str, Tensor]:
        self._check(haystack, "haystack")
        found, vector = self._needle(needle, needle_mask)
        out = {"vector": vector, "needle": torch.sigmoid(self._find(haystack, found))}
        tasks = self.options.tasks
        if "all" in tasks:
            out["all"] = torch.sigmoid(self.decode(self.encode(haystack)))
        if "self" in tasks:
            out["self"] = torch.sigmoid(self._find(needle, found))
        if "spread" in tasks and second is not None:
            self._check(second, "second")
            out["second"] = self.responses(self.encode(second), self._pooling_mask(second, second_mask, "second"))[-1]
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
