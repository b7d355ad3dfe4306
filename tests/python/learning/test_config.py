"""TrainConfig: validated, written as JSON, read back, unknown keys refused."""

from __future__ import annotations

import json
import math

import pytest

from earcore.errors import ConfigError
from earcore.learning.config import TrainConfig, load_config


def test_round_trip(tmp_path):
    config = TrainConfig(network="cascade", steps=100, minutes=None, batch_size=8, loss_weights={"mask": 2.0}, network_options={"width": 0.5})
    path = config.save(tmp_path / "run" / "config.json")
    assert load_config(path) == config
    assert json.loads(path.read_text())["batch_size"] == 8


def test_unknown_keys_are_refused_by_name(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"network": "multi", "batch": 8}))
    with pytest.raises(ConfigError, match="'batch'"):
        load_config(path)
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_config(path)


@pytest.mark.parametrize(
    "changes, name",
    [
        ({"batch_size": 0}, "batch_size"),
        ({"lr_start": 1e-5, "lr_end": 1e-3}, "lr_end"),
        ({"optimiser": "rmsprop"}, "optimiser"),
        ({"steps": None, "minutes": None}, "steps or minutes"),
        ({"device": "tpu"}, "device"),
        ({"threads": True}, "threads"),
        ({"minutes": float("nan")}, "minutes"),
        ({"loss_weights": {"mask": -1}}, "loss_weights"),
        ({"notes": {"x": object()}}, "plain JSON"),
    ],
)
def test_bad_values_name_the_setting(changes, name):
    with pytest.raises(ConfigError, match=name):
        TrainConfig(**changes)


def test_schedule_runs_from_start_to_end():
    config = TrainConfig(steps=100, lr_start=1e-3, lr_end=1e-6)
    assert config.learning_rate(0.0) == pytest.approx(1e-3)
    assert config.learning_rate(1.0) == pytest.approx(1e-6)
    assert config.learning_rate(0.25) == pytest.approx(1e-6 + 0.5 * (1e-3 - 1e-6) * (1 + math.cos(math.pi / 4)))  # cosine, the default
    assert config.replace(schedule="exponential").learning_rate(0.5) == pytest.approx(math.sqrt(1e-3 * 1e-6))
    assert config.replace(schedule="linear").learning_rate(0.5) == pytest.approx((1e-3 + 1e-6) / 2)
    assert config.replace(schedule="cosine").learning_rate(0.5) == pytest.approx((1e-3 + 1e-6) / 2)
    both = TrainConfig(steps=100, minutes=10.0)
    assert both.progress(10, 300.0) == pytest.approx(0.5)  # time is further along than steps
    assert both.progress(80, 60.0) == pytest.approx(0.8)
