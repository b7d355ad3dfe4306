"""ONNX export: every pose network gives onnxruntime's outputs within 1e-4 of torch's,
for any batch size."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")

from earcore.learning.export import export_onnx, onnx_parity, run_onnx  # noqa: E402
from earcore.pose.networks import NETWORKS, build_network  # noqa: E402


def randomise_normalisation(model: torch.nn.Module, seed: int) -> None:
    """Non-trivial batch-norm statistics, so that folding them in is checked too."""
    g = torch.Generator().manual_seed(seed)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(0.1 * torch.randn(m.num_features, generator=g))
            m.running_var.copy_(0.5 + torch.rand(m.num_features, generator=g))
            m.weight.data.copy_(0.5 + torch.rand(m.num_features, generator=g))


@pytest.mark.parametrize("name", NETWORKS)
def test_parity_per_network(tmp_path, name):
    net = build_network(name, {"num_keypoints": 7, "num_robots": 3}, preset="small")
    randomise_normalisation(net, 1)
    net.set_output_statistics(torch.tensor([0.1, -0.2, 2.5]), torch.tensor([0.4, 0.3, 0.6]))
    path = tmp_path / f"{name}.onnx"
    names = export_onnx(net, path, (3, 106, 128))
    assert names[:3] == ["mask_logits", "keypoints", "base"]
    image = torch.rand(3, 3, 106, 128, generator=torch.Generator().manual_seed(2))
    diff = onnx_parity(net, path, image)
    assert set(diff) == set(names)
    assert max(diff.values()) <= 1e-4, diff
    one = run_onnx(path, image[:1].numpy())  # the batch axis is dynamic
    assert one["keypoints"].shape == (1, 7, 3)
    with torch.no_grad():
        expected = net.eval()(image[:1])["keypoints"].numpy()
    assert np.abs(one["keypoints"] - expected).max() <= 1e-4
