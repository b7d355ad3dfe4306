"""Freezing: after optimiser steps (Adam with weight decay) every frozen parameter and
every frozen batch-norm layer's running statistics are bit-identical; the trainable
ones moved; names that match nothing and a network with nothing left to train are
clear errors."""

from __future__ import annotations

import pytest
import torch

from earcore.errors import ConfigError
from earcore.learning.combiners import FixedWeights
from earcore.learning.config import TrainConfig
from earcore.learning.freeze import freeze
from earcore.learning.losses import joint_loss
from earcore.learning.train import train


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.features = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1), torch.nn.BatchNorm2d(4), torch.nn.ReLU())
        self.head = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(64, 6))

    def forward(self, image):
        return {"keypoints": self.head(self.features(image)).view(-1, 2, 3)}


class Data(torch.utils.data.Dataset):
    def __init__(self):
        g = torch.Generator().manual_seed(0)
        self.x, self.y = torch.rand(16, 3, 4, 4, generator=g), torch.randn(16, 2, 3, generator=g)

    def __len__(self):
        return 16

    def __getitem__(self, i):
        return {"image": self.x[i], "keypoints": self.y[i], "keypoint_valid": torch.ones(2, dtype=torch.bool)}


class Objective:
    def inputs(self, batch):
        return (batch["image"],)

    def losses(self, batch, outputs):
        return {"joints": joint_loss(outputs["keypoints"], batch["keypoints"], batch["keypoint_valid"])}


CONFIG = TrainConfig(network="tiny", steps=5, minutes=None, batch_size=4, weight_decay=0.1, eval_every_minutes=None, threads=1)


def test_frozen_parameters_and_batch_norm_statistics_do_not_move(tmp_path):
    net = Net()
    report = freeze(net, ["head"])
    assert report.trainable_count == 64 * 6 + 6 and "features.0.weight" in report.frozen
    before = {k: v.clone() for k, v in net.state_dict().items()}
    train(net, Objective(), Data(), CONFIG, tmp_path / "run", combiner=FixedWeights({"joints": 1.0}), progress=False, log=None)
    after = net.state_dict()
    for key in ("features.0.weight", "features.0.bias", "features.1.weight", "features.1.bias", "features.1.running_mean", "features.1.running_var"):
        assert torch.equal(before[key], after[key]), key
    assert not torch.equal(before["head.1.weight"], after["head.1.weight"])


def test_unfrozen_batch_norm_still_tracks_statistics(tmp_path):
    net = Net()
    freeze(net, [""])
    before = net.features[1].running_mean.clone()
    train(net, Objective(), Data(), CONFIG, tmp_path / "run", combiner=FixedWeights({"joints": 1.0}), progress=False, log=None)
    assert not torch.equal(before, net.features[1].running_mean)


def test_names_that_match_nothing_and_nothing_to_train(tmp_path):
    with pytest.raises(ConfigError, match="features, head"):
        freeze(Net(), ["heads"])
    net = Net()
    for p in net.parameters():
        p.requires_grad_(False)
    with pytest.raises(ConfigError, match="nothing to train"):
        train(net, Objective(), Data(), CONFIG, tmp_path / "run", combiner=FixedWeights({"joints": 1.0}), progress=False, log=None)


def test_statistics_without_parameters_are_held_and_a_second_freeze_replaces_the_first():
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.BatchNorm2d(4, affine=False), torch.nn.Flatten(), torch.nn.Linear(16, 2))
    freeze(net, ["3"])
    net.train()
    before = net[1].running_mean.clone()
    net(torch.rand(4, 3, 4, 4))
    assert torch.equal(before, net[1].running_mean), "a frozen part's batch norm without parameters drifted"
    freeze(net, [""])
    net.train()
    net(torch.rand(4, 3, 4, 4))
    assert not torch.equal(before, net[1].running_mean), "unfrozen again, its statistics must follow the data"
