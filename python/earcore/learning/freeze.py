"""Which parts of a network train: freeze everything but the named modules.

Transfer learning (Papers VI and VII) keeps the transferred convolutions fixed and
retrains the rest. `freeze(model, trainable)` leaves `requires_grad` on only for the
parameters under the named module paths ("joints_head", "red_b.1", ...; "" for
everything) and holds every batch-normalisation layer whose parameters are all frozen
in evaluation mode (a layer outside every named path, with or without parameters), so
its running statistics stay as transferred (in training mode
they would drift to the new images' and change the frozen features). A frozen
parameter is not given to the optimiser, so it stays bit-identical.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from torch import nn

from earcore.errors import ConfigError

__all__ = ["Frozen", "freeze"]


@dataclass(frozen=True)
class Frozen:
    trainable: tuple[str, ...]
    frozen: tuple[str, ...]
    trainable_count: int
    frozen_count: int

    def describe(self) -> str:
        total = self.trainable_count + self.frozen_count
        return f"{self.trainable_count:,} of {total:,} parameters train ({', '.join(self.trainable) or 'none'}); {len(self.frozen)} tensors frozen"


def _under(name: str, prefix: str) -> bool:
    return prefix == "" or name == prefix or name.startswith(prefix + ".")


def _hold_in_eval(module: nn.Module, _inputs: Any) -> None:
    module.training = False


def freeze(model: nn.Module, trainable: Sequence[str]) -> Frozen:
    """Freeze every parameter of `model` not under one of the module paths `trainable`."""
    prefixes = [str(p) for p in trainable]
    names = [n for n, _ in model.named_parameters()]
    unknown = [p for p in prefixes if not any(_under(n, p) for n in names)]
    if unknown:
        tops = sorted({n.split(".")[0] for n in names})
        raise ConfigError(f"no parameters under {unknown}; the network's modules: {', '.join(tops)}")
    on: list[str] = []
    off: list[str] = []
    on_count = off_count = 0
    for name, p in model.named_parameters():
        keep = any(_under(name, q) for q in prefixes)
        p.requires_grad_(keep)
        (on if keep else off).append(name)
        if keep:
            on_count += p.numel()
        else:
            off_count += p.numel()
    for handle in getattr(model, "_earcore_frozen_norms", []):  # an earlier freeze's holds
        handle.remove()
    holds = []
    for path, module in model.named_modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm) and not any(_under(path, q) or _under(q, path) for q in prefixes):
            holds.append(module.register_forward_pre_hook(_hold_in_eval))
            module.eval()
    object.__setattr__(model, "_earcore_frozen_norms", holds)
    return Frozen(tuple(prefixes), tuple(off), on_count, off_count)
