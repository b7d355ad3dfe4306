"""Every loss combiner's weights on synthetic loss sequences against values computed
by hand (plain Python arithmetic, independent of the module's tensor code)."""

from __future__ import annotations

import math

import pytest
import torch

from earcore.errors import ConfigError
from earcore.learning.combiners import COMBINERS, AuxNet, DynamicWeightAverage, FixedWeights, KGCWeights, RunningStats, UncertaintyWeights, combiner_for
from earcore.learning.losses import PAPER_V_WEIGHTS

NAMES = ["iou", "distance"]


def as_tensors(values: dict[str, float]) -> dict[str, torch.Tensor]:
    return {k: torch.tensor(v) for k, v in values.items()}


def weighted_stats(xs: list[float], decay: float) -> tuple[float, float]:
    """Mean and variance with weights a·decay^(t-k) (the first value decay^(t-1))."""
    a, t = 1.0 - decay, len(xs)
    w = [decay ** (t - 1)] + [a * decay ** (t - 1 - k) for k in range(1, t)]
    assert math.isclose(sum(w), 1.0)
    mean = sum(wi * x for wi, x in zip(w, xs))
    return mean, sum(wi * (x - mean) ** 2 for wi, x in zip(w, xs))


SEQUENCE = [(0.9, 40.0), (0.8, 35.0), (0.85, 20.0), (0.6, 22.0), (0.55, 10.0), (0.5, 12.0)]


def test_fixed_weights_are_eq8_and_refuse_unweighted_losses():
    losses = as_tensors({"mask": 0.2, "joints": 0.1, "base": 0.05, "type": 1.0})
    total, weights = FixedWeights(PAPER_V_WEIGHTS)(losses)
    assert float(total) == pytest.approx(1.0 * 0.2 + 1.5 * 0.1 + 1.5 * 0.05 + 0.3 * 1.0)
    assert weights == PAPER_V_WEIGHTS
    with pytest.raises(ConfigError, match="extra"):
        FixedWeights(PAPER_V_WEIGHTS)({**losses, "extra": torch.tensor(1.0)})
    with pytest.raises(ConfigError, match="mask"):
        FixedWeights({"mask": -1.0})
    total, weights = combiner_for("sum", NAMES)(as_tensors({"iou": 0.5, "distance": 3.0}))
    assert float(total) == pytest.approx(3.5) and weights == {"iou": 1.0, "distance": 1.0}


def test_running_stats_are_the_exponentially_weighted_mean_and_variance():
    stats = RunningStats(NAMES, decay=0.8)
    for t, (iou, dist) in enumerate(SEQUENCE, 1):
        stats.add({"iou": iou, "distance": dist})
        for j, name in enumerate(NAMES):
            mean, var = weighted_stats([s[j] for s in SEQUENCE[:t]], 0.8)
            assert float(stats.mean[j]) == pytest.approx(mean, rel=1e-12), name
            assert float(stats.var[j]) == pytest.approx(var, rel=1e-12, abs=1e-15), name
    with pytest.raises(FloatingPointError):
        stats.add({"iou": float("nan"), "distance": 1.0})


@pytest.mark.parametrize("name, epsilon, by_mean", [("kgc", 0.0, False), ("kgc-eps", 1e-3, False), ("kgc-mean", 0.0, True)])
def test_kgc_variants_weigh_by_the_running_variance(name, epsilon, by_mean):
    combiner = combiner_for(name, NAMES, decay=0.8, warmup=3)
    current = {"iou": 0.45, "distance": 9.0}
    for t, (iou, dist) in enumerate(SEQUENCE, 1):
        total, weights = combiner(as_tensors(current))
        if t <= 3:  # fewer than `warmup` steps seen: the plain sum
            assert weights == {"iou": 1.0, "distance": 1.0}
            assert float(total) == pytest.approx(sum(current.values()))
        else:
            spreads = []
            for j, n in enumerate(NAMES):
                mean, var = weighted_stats([s[j] for s in SEQUENCE[: t - 1]], 0.8)
                s = var + epsilon
                if by_mean:
                    s /= mean
                spreads.append(s)
                assert weights[n] == pytest.approx(1.0 / (2.0 * s), rel=1e-9)
            expected = sum(current[n] / (2.0 * s) + math.log(s) for n, s in zip(NAMES, spreads))
            assert float(total) == pytest.approx(expected, rel=1e-6)
        combiner.update({"iou": iou, "distance": dist})


def test_kgc_gives_the_low_variance_loss_an_extreme_weight_and_eps_bounds_it():
    """The paper's Table I: KGC's weights explode on a loss that hardly varies; ε caps them at 1/(2ε)."""
    plain, guarded = KGCWeights(NAMES, warmup=2), KGCWeights(NAMES, epsilon=1e-3, warmup=2)
    for k in range(30):
        step = {"iou": 1.0 - 1e-6 * (k % 2), "distance": 30.0 + 5.0 * (k % 3)}
        plain.update(step)
        guarded.update(step)
    _, w = plain(as_tensors({"iou": 1.0, "distance": 30.0}))
    _, g = guarded(as_tensors({"iou": 1.0, "distance": 30.0}))
    assert w["iou"] / w["distance"] > 1e6
    assert g["iou"] <= 1.0 / (2e-3) and g["iou"] / g["distance"] < w["iou"] / w["distance"]


def test_dwa_uses_the_ratio_of_the_last_two_periods():
    dwa = DynamicWeightAverage(NAMES, period=2, temperature=2.0)
    sequence = [(1.0, 10.0), (0.8, 10.0), (0.6, 9.0), (0.4, 7.0), (0.3, 5.0)]
    for k, (iou, dist) in enumerate(sequence):
        _, w = dwa(as_tensors({"iou": 0.5, "distance": 5.0}))
        if k < 4:
            assert w == {"iou": 1.0, "distance": 1.0}
        dwa.update({"iou": iou, "distance": dist})
    # periods: (1.0, 0.8) → 0.9 and (0.6, 0.4) → 0.5 for iou; 10, 8 for distance; the fifth step starts a new period
    r_iou, r_dist = 0.5 / 0.9, 8.0 / 10.0
    e_iou, e_dist = math.exp(r_iou / 2.0), math.exp(r_dist / 2.0)
    _, w = dwa(as_tensors({"iou": 0.5, "distance": 5.0}))
    assert w["iou"] == pytest.approx(2.0 * e_iou / (e_iou + e_dist))
    assert w["distance"] == pytest.approx(2.0 * e_dist / (e_iou + e_dist))
    assert w["iou"] < w["distance"]  # the faster-falling loss gets less weight


def test_uncertainty_weighting_is_trained_by_the_network_optimiser_to_its_minimum():
    combiner = UncertaintyWeights(NAMES)
    losses = as_tensors({"iou": 0.5, "distance": 8.0})
    total, w = combiner(losses)
    assert float(total.detach()) == pytest.approx(0.5 * 0.5 + 0.5 * 8.0)
    assert w == {"iou": 0.5, "distance": 0.5}
    assert combiner.network_parameters() == [combiner.log_var]
    optimiser = torch.optim.Adam(combiner.network_parameters(), lr=0.05)
    for _ in range(2000):
        optimiser.zero_grad()
        combiner(losses)[0].backward()
        optimiser.step()
    # the minimum of ½ e^(-s) L + ½ s is at e^s = L
    assert torch.exp(combiner.log_var).tolist() == pytest.approx([0.5, 8.0], rel=1e-3)


def test_auxnet_starts_as_the_sum_then_weighs_by_its_outputs():
    aux = AuxNet(NAMES, warmup=2, seed=3)
    current = {"iou": 0.7, "distance": 12.0}
    assert aux(as_tensors(current))[1] == {"iou": 1.0, "distance": 1.0}
    for iou, dist in SEQUENCE[:3]:
        aux.update({"iou": iou, "distance": dist})
    # its inputs: the current value, the running mean and standard deviation per loss
    x = aux.inputs(current).view(2, 3)
    for j, n in enumerate(NAMES):
        mean, var = weighted_stats([s[j] for s in SEQUENCE[:3]], 0.98)
        assert x[j].tolist() == pytest.approx([current[n], mean, math.sqrt(var)], rel=1e-6)
    with torch.no_grad():
        w = torch.nn.functional.softplus(aux.outputs(x.reshape(-1))) + 1e-6
    total, weights = aux(as_tensors(current))
    assert weights["iou"] == pytest.approx(1.0 / float(w[0]), rel=1e-6)
    assert weights["distance"] == pytest.approx(1.0 / float(w[1]), rel=1e-6)
    expected = current["iou"] / float(w[0]) + math.log(float(w[0])) + current["distance"] / float(w[1]) + math.log(float(w[1]))
    assert float(total) == pytest.approx(expected, rel=1e-5)


def test_auxnet_objective_is_the_relative_change_of_the_total():
    aux = AuxNet(NAMES, warmup=2, seed=1)
    for iou, dist in SEQUENCE[:4]:
        aux.update({"iou": iou, "distance": dist})
    losses = {"iou": 0.5, "distance": 11.0}
    with torch.no_grad():
        w = aux.raw_weights(losses).double()
    total = 0.5 / float(w[0]) + math.log(float(w[0])) + 11.0 / float(w[1]) + math.log(float(w[1]))
    mean = float(aux.total_mean)
    assert float(aux.objective(losses).detach()) == pytest.approx((total - mean) / mean, rel=1e-5)


def test_auxnet_learns_each_weight_towards_its_loss():
    """For steady losses Eq. 2's minimum over w is w_i = L_i: AuxNet's own optimiser gets there."""
    aux = AuxNet(NAMES, warmup=2, lr=0.01, seed=0)
    steady = {"iou": 0.3, "distance": 6.0}
    for _ in range(3000):
        aux.update(steady)
    w = aux.raw_weights(steady).tolist()
    assert w == pytest.approx([0.3, 6.0], rel=0.05)


def test_auxnet_takes_no_gradient_from_the_network_loss_and_none_to_the_network():
    aux = AuxNet(NAMES, warmup=2)
    aux.update({"iou": 0.4, "distance": 5.0})
    aux.update({"iou": 0.3, "distance": 4.0})
    aux.optimiser.zero_grad(set_to_none=True)
    p = torch.tensor(2.0, requires_grad=True)
    losses = {"iou": p * 0.2, "distance": p * 3.0}
    total, weights = aux(losses)
    total.backward()
    assert all(q.grad is None for q in aux.parameters())
    assert float(p.grad) == pytest.approx(0.2 * weights["iou"] + 3.0 * weights["distance"], rel=1e-6)
    assert aux.network_parameters() == []


def test_learned_state_round_trips_through_the_state_dict():
    options = {"kgc": {}, "dwa": {"period": 5}, "auxnet": {}, "uncertainty": {}}
    for name, extra in options.items():
        a, b = combiner_for(name, NAMES, seed=5, **extra), combiner_for(name, NAMES, seed=6, **extra)
        for iou, dist in SEQUENCE * 10:
            a.update({"iou": iou, "distance": dist})
        if name == "uncertainty":
            with torch.no_grad():
                a.log_var.copy_(torch.tensor([0.3, -1.2]))
        losses = as_tensors({"iou": 0.5, "distance": 7.0})
        assert a(losses)[1] != b(losses)[1], f"{name}: learned nothing, the round trip would prove nothing"
        b.load_state_dict(a.state_dict())
        assert a(losses)[1] == b(losses)[1], name
        if name == "auxnet":
            assert b.optimiser.state_dict()["state"], "AuxNet's Adam state travels with it"


def test_names_options_and_losses_are_checked():
    assert set(COMBINERS) == {"fixed", "sum", "kgc", "kgc-eps", "kgc-mean", "uncertainty", "dwa", "auxnet"}
    with pytest.raises(ConfigError, match="one of"):
        combiner_for("magic", NAMES)
    with pytest.raises(ConfigError, match="period"):
        combiner_for("kgc", NAMES, period=3)
    with pytest.raises(ConfigError, match="distinct"):
        combiner_for("kgc", ["a", "a"])
    with pytest.raises(ConfigError, match="missing"):
        combiner_for("kgc", NAMES)(as_tensors({"iou": 1.0}))
    with pytest.raises(ConfigError, match="decay"):
        combiner_for("auxnet", NAMES, decay=1.0)
    with pytest.raises(ConfigError, match="warmup"):
        combiner_for("kgc", NAMES, warmup=0)
    with pytest.raises(ConfigError, match="warmup"):
        combiner_for("auxnet", NAMES, warmup=20.5)
    with pytest.raises(ConfigError, match="epsilon"):
        combiner_for("kgc-eps", NAMES, epsilon="abc")
