"""How named losses become one total: one interface for every multi-objective network.

Every combiner maps the batch's named losses to (total, the weights used) in
`forward`, which changes nothing, and learns from the losses in `update`, which the
training loop calls once after each optimiser step with the (detached) losses of that
step. Schemes (`combiner_for`):

- ``fixed``: a weight per loss (the papers' Eq. 8); ``sum``: every weight 1.
- ``kgc``: Kendall, Gal & Cipolla as the IROS 2018 paper measured it (its Eq. 1):
  ``Σ L_i / (2 σ_i²) + log σ_i²`` with σ_i² the running variance of L_i over the run
  (an exponentially weighted variance, `RunningStats`). Low variance gives a high
  weight, unboundedly: the paper's exploding weights.
- ``kgc-eps``: the same with ε = 1e-3 added to each variance.
- ``kgc-mean``: the variance divided by the loss's running mean (σ_i²/μ_i), which
  needs no rescaling of the losses.
- ``uncertainty``: Kendall et al.'s learned form, ``Σ ½ e^(-s_i) L_i + ½ s_i`` with
  s_i = log σ_i² a parameter trained with the network.
- ``dwa``: Dynamic Weight Average (Liu, Johns & Davison 2019) over periods of
  `period` steps: ``w_i = K softmax(r / T)_i``, r_i the ratio of L_i's mean over the
  last period to the one before.
- ``auxnet``: the IROS 2018 AuxNet (`AuxNet`).

The running-statistic schemes (kgc*, dwa, auxnet) use weight 1 for every loss until
they have seen `warmup` steps (a variance of two values is no estimate).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from earcore.errors import ConfigError

__all__ = [
    "COMBINERS",
    "AuxNet",
    "DynamicWeightAverage",
    "FixedWeights",
    "KGCWeights",
    "LossCombiner",
    "RunningStats",
    "UncertaintyWeights",
    "combiner_for",
]

COMBINERS = ("fixed", "sum", "kgc", "kgc-eps", "kgc-mean", "uncertainty", "dwa", "auxnet")

#: A variance this small stands for zero (KGC's weight 1/(2σ²) stays finite, if huge).
_TINY_VARIANCE = 1e-12


def _names(names: Sequence[str]) -> list[str]:
    out = [str(n) for n in names]
    if not out:
        raise ConfigError("a loss combiner needs the names of the losses it combines")
    if len(set(out)) != len(out):
        raise ConfigError(f"loss names must be distinct, got {out}")
    return out


def _number(value: Tensor | float) -> float:
    return float(value.detach()) if isinstance(value, Tensor) else float(value)


def _check_warmup(warmup: int) -> int:
    if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 2:
        raise ConfigError(f"warmup must be a whole number of steps >= 2 (a variance needs two losses), got {warmup!r}")
    return warmup


def _check_decay(decay: float) -> float:
    if isinstance(decay, bool) or not isinstance(decay, (int, float)) or not 0.0 < decay < 1.0:
        raise ConfigError(f"decay must be in (0, 1), got {decay!r}")
    return float(decay)


class LossCombiner(nn.Module):
    """Named losses → (total, the weights used).

    Subclasses implement `weights` (the factor on each loss in the total) and may add
    a term through `extra`; learned schemes learn in `update` (running statistics, an
    own optimiser) or hold parameters the network's optimiser trains
    (`network_parameters`)."""

    def __init__(self, names: Sequence[str]):
        super().__init__()
        self.names = _names(names)

    def weights(self, losses: Mapping[str, Tensor]) -> dict[str, Tensor | float]:
        raise NotImplementedError

    def extra(self, losses: Mapping[str, Tensor]) -> Tensor | None:
        """A term added to the weighted sum (e.g. a variance's logarithm)."""
        return None

    def network_parameters(self) -> list[nn.Parameter]:
        """Parameters the network's optimiser trains with the network (none by default)."""
        return []

    def update(self, losses: Mapping[str, float]) -> None:
        """Learn from one training step's losses (after the optimiser's step)."""

    def check(self, losses: Mapping[str, Any]) -> None:
        if not losses:
            raise ValueError("no losses to combine")
        if set(losses) != set(self.names):
            missing, unknown = sorted(set(self.names) - set(losses)), sorted(set(losses) - set(self.names))
            raise ConfigError(f"the combiner was built for losses {self.names}; missing {missing}, unknown {unknown}")

    def forward(self, losses: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        self.check(losses)
        w = self.weights(losses)
        total = sum((w[name] * losses[name] for name in self.names), torch.zeros((), device=next(iter(losses.values())).device))
        more = self.extra(losses)
        if more is not None:
            total = total + more
        return total, {name: _number(w[name]) for name in self.names}


class FixedWeights(LossCombiner):
    """Eq. 8: a fixed weight per named loss; a loss with no weight is an error (so a new
    objective is never silently left out or counted once)."""

    def __init__(self, weights: Mapping[str, float]):
        for name, value in weights.items():
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"loss weight {name!r} must be a finite number >= 0, got {value!r}")
        super().__init__(list(weights))
        self.fixed = {str(k): float(v) for k, v in weights.items()}

    def check(self, losses: Mapping[str, Any]) -> None:
        if not losses:
            raise ValueError("no losses to combine")
        missing = sorted(set(losses) - set(self.fixed))
        if missing:
            raise ConfigError(f"no weight for loss(es) {missing}; weights given: {sorted(self.fixed)}")

    def forward(self, losses: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        self.check(losses)
        total = sum((self.fixed[name] * value for name, value in losses.items()), torch.zeros((), device=next(iter(losses.values())).device))
        return total, {name: self.fixed[name] for name in losses}


class RunningStats(nn.Module):
    """Exponentially weighted mean and variance of each named loss over training steps.

    The first value starts the mean (variance 0); then, with α = 1 - decay,
    ``δ = x - m; m += α δ; v = (1 - α)(v + α δ²)`` (Finch 2009): m and v are exactly
    the mean and variance of the values seen, weighted α(1-α)^(t-k) (the first
    (1-α)^(t-1))."""

    count: Tensor
    mean: Tensor
    var: Tensor

    def __init__(self, names: Sequence[str], decay: float):
        super().__init__()
        self.names = _names(names)
        self.decay = _check_decay(decay)
        k = len(self.names)
        self.register_buffer("count", torch.zeros((), dtype=torch.long))
        self.register_buffer("mean", torch.zeros(k, dtype=torch.float64))
        self.register_buffer("var", torch.zeros(k, dtype=torch.float64))

    def vector(self, losses: Mapping[str, Any]) -> Tensor:
        return torch.tensor([float(losses[n]) for n in self.names], dtype=torch.float64, device=self.mean.device)

    def add(self, losses: Mapping[str, Any]) -> None:
        x = self.vector(losses)
        if not torch.isfinite(x).all():
            raise FloatingPointError(f"a loss is not finite: { {n: float(v) for n, v in zip(self.names, x.tolist())} }")
        if int(self.count) == 0:
            self.mean.copy_(x)
            self.var.zero_()
        else:
            a = 1.0 - self.decay
            d = x - self.mean
            self.mean.add_(a * d)
            self.var.copy_((1.0 - a) * (self.var + a * d * d))
        self.count.add_(1)

    @property
    def std(self) -> Tensor:
        return self.var.clamp(min=0.0).sqrt()


class KGCWeights(LossCombiner):
    """KGC as the IROS 2018 paper measured it (its Eq. 1), and its two guarded variants:
    ``Σ L_i / (2 s_i) + log s_i`` with s_i the running variance of L_i (`RunningStats`),
    plus `epsilon` ("kgc-eps": 1e-3), or divided by the running mean (`by_mean`,
    "kgc-mean"). The log term carries no gradient; it is part of the reported total."""

    def __init__(self, names: Sequence[str], *, epsilon: float = 0.0, by_mean: bool = False, decay: float = 0.98, warmup: int = 20):
        super().__init__(names)
        if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float)) or not (math.isfinite(epsilon) and epsilon >= 0):
            raise ConfigError(f"epsilon must be a finite number >= 0, got {epsilon!r}")
        self.epsilon, self.by_mean, self.warmup = float(epsilon), bool(by_mean), _check_warmup(warmup)
        self.stats: RunningStats = RunningStats(self.names, decay)

    def spread(self) -> Tensor:
        """s_i: the variance (+ ε, or / mean) per loss, floored at 1e-12."""
        s = self.stats.var + self.epsilon
        if self.by_mean:
            s = s / self.stats.mean.abs().clamp(min=_TINY_VARIANCE)
        return s.clamp(min=_TINY_VARIANCE)

    def ready(self) -> bool:
        return int(self.stats.count) >= self.warmup

    def weights(self, losses: Mapping[str, Tensor]) -> dict[str, Tensor | float]:
        if not self.ready():
            return {n: 1.0 for n in self.names}
        w = (0.5 / self.spread()).tolist()
        return dict(zip(self.names, w))

    def extra(self, losses: Mapping[str, Tensor]) -> Tensor | None:
        if not self.ready():
            return None
        device = next(iter(losses.values())).device
        return torch.tensor(float(self.spread().log().sum()), device=device)

    def update(self, losses: Mapping[str, float]) -> None:
        self.stats.add(losses)


class UncertaintyWeights(LossCombiner):
    """Kendall, Gal & Cipolla's learned homoscedastic uncertainty:
    ``Σ ½ e^(-s_i) L_i + ½ s_i``, s_i = log σ_i² trained with the network (start 0:
    weights ½). For fixed L_i the minimum is at e^(s_i) = L_i."""

    def __init__(self, names: Sequence[str]):
        super().__init__(names)
        self.log_var = nn.Parameter(torch.zeros(len(self.names)))

    def network_parameters(self) -> list[nn.Parameter]:
        return [self.log_var]

    def weights(self, losses: Mapping[str, Tensor]) -> dict[str, Tensor | float]:
        w = 0.5 * torch.exp(-self.log_var)
        return {n: w[i] for i, n in enumerate(self.names)}

    def extra(self, losses: Mapping[str, Tensor]) -> Tensor | None:
        return 0.5 * self.log_var.sum()


class DynamicWeightAverage(LossCombiner):
    """DWA (Liu et al., CVPR 2019): ``w_i = K exp(r_i / T) / Σ_j exp(r_j / T)`` with r_i
    the ratio of L_i's mean over the last complete period of `period` steps to its mean
    over the period before (the paper's periods are epochs); 1 for every loss until
    two periods are complete."""

    count: Tensor
    running: Tensor
    last: Tensor
    before: Tensor

    def __init__(self, names: Sequence[str], *, period: int = 50, temperature: float = 2.0):
        super().__init__(names)
        if isinstance(period, bool) or not isinstance(period, int) or period < 1:
            raise ConfigError(f"period must be a whole number >= 1, got {period!r}")
        if isinstance(temperature, bool) or not isinstance(temperature, (int, float)) or not (math.isfinite(temperature) and temperature > 0):
            raise ConfigError(f"temperature must be > 0, got {temperature!r}")
        self.period, self.temperature = period, float(temperature)
        k = len(self.names)
        self.register_buffer("count", torch.zeros((), dtype=torch.long))
        self.register_buffer("running", torch.zeros(k, dtype=torch.float64))
        self.register_buffer("last", torch.zeros(k, dtype=torch.float64))
        self.register_buffer("before", torch.zeros(k, dtype=torch.float64))

    def current(self) -> list[float]:
        if int(self.count) < 2 * self.period:
            return [1.0] * len(self.names)
        r = self.last / self.before.clamp(min=_TINY_VARIANCE)
        return (len(self.names) * torch.softmax(r / self.temperature, 0)).tolist()

    def weights(self, losses: Mapping[str, Tensor]) -> dict[str, Tensor | float]:
        return dict(zip(self.names, self.current()))

    def update(self, losses: Mapping[str, float]) -> None:
        self.running.add_(torch.tensor([float(losses[n]) for n in self.names], dtype=torch.float64, device=self.running.device))
        self.count.add_(1)
        if int(self.count) % self.period == 0:
            self.before.copy_(self.last)
            self.last.copy_(self.running / self.period)
            self.running.zero_()


class AuxNet(LossCombiner):
    """The IROS 2018 AuxNet: a small network that weighs the losses online.

    Inputs per loss: its current value, its running mean and running standard
    deviation (`RunningStats`, raw values: the paper does no pre-processing). One
    hidden layer of `hidden` (24) leaky-ReLU units; one output per loss, made positive
    by softplus (+1e-6): w_i. The network trains on
    ``L_total = Σ_i L_i / w_i + ln w_i`` (Eq. 2) with the w_i fixed. AuxNet has its own
    Adam and minimises ``(L_total - L̄_total) / L̄_total`` (Eq. 3 read as the relative
    change of the total against its running mean L̄_total), with the gradient
    reaching it through the w_i in L_total and L̄_total held fixed (docs/design/
    auxnet.md says why). For fixed losses the objective's minimum is w_i = L_i: the
    network then trains on each loss relative to its own size."""

    total_mean: Tensor

    def __init__(self, names: Sequence[str], *, hidden: int = 24, lr: float = 1e-3, decay: float = 0.98, warmup: int = 20, seed: int = 0):
        super().__init__(names)
        if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 1:
            raise ConfigError(f"hidden must be a whole number >= 1, got {hidden!r}")
        if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not (math.isfinite(lr) and lr > 0):
            raise ConfigError(f"lr must be > 0, got {lr!r}")
        self.warmup = _check_warmup(warmup)
        self.stats: RunningStats = RunningStats(self.names, decay)
        self.register_buffer("total_mean", torch.zeros((), dtype=torch.float64))
        k = len(self.names)
        generator = torch.Generator().manual_seed(seed)  # its own draws: the network's initialisation is not shifted
        self.hidden_layer, self.out_layer = nn.Linear(3 * k, hidden), nn.Linear(hidden, k)
        with torch.no_grad():
            for layer in (self.hidden_layer, self.out_layer):
                bound = 1.0 / math.sqrt(layer.in_features)
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.uniform_(-bound, bound, generator=generator)
        self.optimiser = torch.optim.Adam(self.parameters(), lr=lr, betas=(0.9, 0.999), eps=1e-8)

    def outputs(self, x: Tensor) -> Tensor:
        """The network's raw outputs (before softplus) for inputs `x` (3K,)."""
        return self.out_layer(F.leaky_relu(self.hidden_layer(x), 0.01))

    def inputs(self, losses: Mapping[str, Any]) -> Tensor:
        x = self.stats.vector(losses)
        if int(self.stats.count) == 0:
            mean, std = x, torch.zeros_like(x)
        else:
            mean, std = self.stats.mean, self.stats.std
        return torch.stack([x, mean, std], 1).reshape(-1).float()

    def raw_weights(self, losses: Mapping[str, Any]) -> Tensor:
        """w_i (differentiable in AuxNet's parameters)."""
        device = self.hidden_layer.weight.device
        return F.softplus(self.outputs(self.inputs(losses).to(device))) + 1e-6

    def ready(self) -> bool:
        return int(self.stats.count) >= self.warmup

    def weights(self, losses: Mapping[str, Tensor]) -> dict[str, Tensor | float]:
        if not self.ready():
            return {n: 1.0 for n in self.names}
        with torch.no_grad():
            w = self.raw_weights(losses)
        return {n: float(1.0 / w[i]) for i, n in enumerate(self.names)}

    def extra(self, losses: Mapping[str, Tensor]) -> Tensor | None:
        if not self.ready():
            return None
        with torch.no_grad():
            w = self.raw_weights(losses)
        return torch.log(w).sum().to(next(iter(losses.values())).device)

    def objective(self, losses: Mapping[str, Any]) -> Tensor:
        """Eq. 3 for this step's losses (differentiable in AuxNet's parameters)."""
        w = self.raw_weights(losses)
        x = self.stats.vector(losses).to(w)
        total = (x / w + torch.log(w)).sum()
        reference = float(self.total_mean) if int(self.stats.count) > 0 else float(total.detach())
        reference = math.copysign(max(abs(reference), _TINY_VARIANCE), reference)
        return (total - reference) / abs(reference)

    def update(self, losses: Mapping[str, float]) -> None:
        aux = self.objective(losses)
        self.optimiser.zero_grad(set_to_none=True)
        aux.backward()
        self.optimiser.step()
        with torch.no_grad():
            w = self.raw_weights(losses).double()
            total = float((self.stats.vector(losses).to(w) / w + torch.log(w)).sum())
        if int(self.stats.count) == 0:
            self.total_mean.fill_(total)
        else:
            self.total_mean.mul_(self.stats.decay).add_((1.0 - self.stats.decay) * total)
        self.stats.add(losses)

    def get_extra_state(self) -> dict[str, Any]:
        return {"optimiser": self.optimiser.state_dict()}

    def set_extra_state(self, state: Any) -> None:
        if isinstance(state, dict) and "optimiser" in state:
            self.optimiser.load_state_dict(state["optimiser"])


def combiner_for(name: str, names: Sequence[str], *, fixed: Mapping[str, float] | None = None, seed: int = 0, **options: Any) -> LossCombiner:
    """A combiner by name (`COMBINERS`) for the losses `names`; `fixed` holds the
    weights of "fixed" (the network's defaults); `options` go to the scheme
    (decay, warmup, period, temperature, hidden, lr)."""
    if name not in COMBINERS:
        raise ConfigError(f"loss combiner must be one of {', '.join(COMBINERS)}, got {name!r}")
    names = _names(names)
    allowed = {
        "fixed": set(),
        "sum": set(),
        "kgc": {"decay", "warmup"},
        "kgc-eps": {"decay", "warmup", "epsilon"},
        "kgc-mean": {"decay", "warmup"},
        "uncertainty": set(),
        "dwa": {"period", "temperature"},
        "auxnet": {"decay", "warmup", "hidden", "lr"},
    }[name]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ConfigError(f"the {name} combiner takes no option(s) {unknown}; it takes {sorted(allowed) or 'none'}")
    if name == "fixed":
        given = dict(fixed or {})
        missing = sorted(set(names) - set(given))
        if missing:
            raise ConfigError(f"the fixed combiner has no weight for loss(es) {missing}")
        return FixedWeights({n: given[n] for n in names})
    if name == "sum":
        return FixedWeights({n: 1.0 for n in names})
    if name == "kgc":
        return KGCWeights(names, **options)
    if name == "kgc-eps":
        return KGCWeights(names, **{"epsilon": 1e-3, **options})
    if name == "kgc-mean":
        return KGCWeights(names, by_mean=True, **options)
    if name == "uncertainty":
        return UncertaintyWeights(names)
    if name == "dwa":
        return DynamicWeightAverage(names, **options)
    return AuxNet(names, seed=seed, **options)
