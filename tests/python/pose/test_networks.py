"""The pose networks: output shapes at the shipped and the papers' sizes, and each one
can fit one batch of geometrically consistent images."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from earcore.errors import ConfigError
from earcore.learning.combiners import FixedWeights
from earcore.learning.train import collate
from earcore.pose.networks import NETWORKS, build_network
from earcore.pose.objectives import default_weights, objective_for
from earcore.pose.train import fit_statistics

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402


@pytest.mark.parametrize("name", NETWORKS)
@pytest.mark.parametrize("preset, size", [("small", (128, 106)), ("paper", (256, 212))])
def test_output_shapes(name, preset, size):
    net = build_network(name, {"input_size": size, "num_keypoints": 7, "num_robots": 3}, preset=preset).eval()
    w, h = size
    with torch.no_grad():
        out = net(torch.rand(2, 3, h, w))
    assert out["mask_logits"].shape == (2, 1, h, w)
    assert out["keypoints"].shape == (2, 7, 3)
    assert out["base"].shape == (2, 3)
    assert ("type_logits" in out) == (name != "cascade")
    if name != "cascade":
        assert out["type_logits"].shape == (2, 3)
    if name == "keypoint":
        assert out["pixels"].shape == (2, 8, 2)
    with pytest.raises(ValueError, match=f"built for {w}×{h}"):
        net(torch.rand(1, 3, h + 8, w))
    with pytest.raises(ValueError, match=r"\(N, 3, H, W\)"):
        net(torch.rand(1, 1, h, w))


def test_bad_options_are_named():
    with pytest.raises(ConfigError, match="mask_stride"):
        build_network("multi", {"mask_stride": 3})
    with pytest.raises(ConfigError, match="'depth'"):
        build_network("multi", {"depth": 3})
    with pytest.raises(ConfigError, match="network must be"):
        build_network("resnet")


def test_keypoint_network_back_projects_its_pixels():
    net = build_network("keypoint", {"input_size": (64, 48), "num_keypoints": 3, "num_robots": 1, "width": 0.25}).eval()
    k = torch.tensor([[50.0, 0, 31.5], [0, 55.0, 23.5], [0, 0, 1]])
    net.set_camera(k)
    with torch.no_grad():
        out = net(torch.rand(1, 3, 48, 64))
    points = torch.cat([out["keypoints"][0], out["base"]])
    uv = torch.stack([50 * points[:, 0] / points[:, 2] + 31.5, 55 * points[:, 1] / points[:, 2] + 23.5], 1)
    assert torch.allclose(uv, out["pixels"][0], atol=1e-3)


@pytest.mark.parametrize("name", NETWORKS)
def test_one_batch_is_learnt(name):
    torch.manual_seed(0)
    data = FakeDataset(8, 32, 32, keypoints=4)
    batch = collate([data[i] for i in range(8)])
    net = build_network(name, {"input_size": (32, 32), "num_keypoints": 4, "num_robots": 2, "width": 0.5, "fc": 128, "head": 64, "grid": 4})
    fit_statistics(net, data)
    objective = objective_for(name)
    combine = FixedWeights(default_weights(name))
    optimiser = torch.optim.Adam(net.parameters(), lr=3e-3)
    first = None
    for _ in range(200):
        losses = objective.losses(batch, net(*objective.inputs(batch)))
        total, _ = combine(losses)
        first = first if first is not None else {k: float(v.detach()) for k, v in losses.items()}
        optimiser.zero_grad()
        total.backward()
        optimiser.step()
    net.eval()  # what was learnt holds with the running statistics too
    with torch.no_grad():
        out = net(batch["image"], None, batch["intrinsics"])
        last = objective.losses(batch, out)
    assert float(last["joints"]) < 0.03 and float(last["joints"]) < 0.2 * first["joints"], (first, last)
    assert float(last["base"]) < 0.03, (first, last)
    assert float(last["mask"]) < 0.3 * first["mask"], (first, last)
    predicted = out["mask_logits"] > 0
    truth = batch["mask"] > 0.5
    assert (predicted & truth).sum() / (predicted | truth).sum() > 0.6
    if "type_logits" in out:
        assert (out["type_logits"].argmax(1) == batch["robot"]).all()
