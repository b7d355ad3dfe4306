"""estimate() with onnxruntime gives the torch network's answers, corrected for other
image sizes and focal lengths by the rule its module documents; bad input is named."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")

from earcore.pose import (  # noqa: E402
    PoseWeightsError,
    estimate,
    inference,  # noqa: E402
)
from earcore.pose.export import export_network  # noqa: E402
from earcore.pose.networks import build_network  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402

DATA = FakeDataset(2, 32, 32, keypoints=4)


def exported(tmp_path, name):
    torch.manual_seed(1)
    net = build_network(name, {"input_size": (32, 32), "num_keypoints": 4, "num_robots": 2, "width": 0.25, "fc": 32, "head": 16, "grid": 4})
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    net.set_output_statistics(torch.tensor([0.0, -0.1, 2.0]), torch.tensor([0.3, 0.3, 0.4]))
    net.set_camera(torch.as_tensor(DATA.intrinsics))
    path = tmp_path / f"{name}.onnx"
    sidecar = export_network(net.eval(), {"robots": DATA.robots, "keypoints": DATA.manifest["keypoints"]}, path)
    assert max(sidecar["parity"].values()) <= 1e-4
    return net.eval(), path


def torch_outputs(net, image_hwc):
    with torch.no_grad():
        return {k: v[0].numpy() for k, v in net(torch.from_numpy(image_hwc.transpose(2, 0, 1)[None].astype(np.float32))).items()}


@pytest.mark.parametrize("name", ["multi", "keypoint"])
def test_same_outputs_as_torch(tmp_path, name):
    net, path = exported(tmp_path, name)
    image = DATA[0]["image"].numpy().transpose(1, 2, 0).astype(np.float64)
    expected = torch_outputs(net, image)
    result = estimate(image, DATA.intrinsics, weights=path)
    probabilities = np.exp(expected["type_logits"]) / np.exp(expected["type_logits"]).sum()
    assert result.robot == DATA.robots[int(np.argmax(probabilities))]
    assert result.probabilities[DATA.robots[1]] == pytest.approx(probabilities[1], abs=1e-5)
    count = len(DATA.manifest["keypoints"][result.robot])
    assert result.keypoints.shape == (count, 3) and result.keypoint_names == DATA.manifest["keypoints"][result.robot]
    assert np.abs(result.keypoints - expected["keypoints"][:count]).max() < 1e-4
    assert np.abs(result.base - expected["base"]).max() < 1e-4
    logits = expected["mask_logits"][0]
    sure = np.abs(logits) > 1e-3
    assert np.array_equal(result.mask[sure], (logits > 0)[sure])
    k = DATA.intrinsics
    uv = k[0, 0] * result.keypoints[:, 0] / result.keypoints[:, 2] + k[0, 2]
    assert np.abs(result.pixels[:, 0] - uv).max() < 1e-3
    if name == "keypoint":
        assert np.abs(result.pixels - expected["pixels"][:count]).max() < 1e-3
    # uint8 input is read as value / 255
    as_bytes = np.rint(image * 255).astype(np.uint8)
    again = estimate(as_bytes, DATA.intrinsics, weights=path)
    assert np.abs(again.keypoints - torch_outputs(net, as_bytes / 255.0)["keypoints"][:count]).max() < 1e-4


def test_other_sizes_and_focal_lengths(tmp_path):
    net, path = exported(tmp_path, "multi")
    image = DATA[1]["image"].numpy().transpose(1, 2, 0).astype(np.float64)
    k = DATA.intrinsics
    same = estimate(image, k, weights=path)
    # twice the size, every pixel repeated: box-averaged back to the same input; the camera scales with it
    big = image.repeat(2, 0).repeat(2, 1)
    k2 = k.copy()
    k2[:2, :2] *= 2
    k2[:2, 2] = (k[:2, 2] + 0.5) * 2 - 0.5
    doubled = estimate(big, k2, weights=path)
    assert np.abs(doubled.keypoints - same.keypoints).max() < 1e-5
    assert np.abs(doubled.pixels - ((same.pixels + 0.5) * 2 - 0.5)).max() < 1e-4
    assert doubled.mask.shape == (64, 64)
    assert estimate(big, None, weights=path).keypoints == pytest.approx(doubled.keypoints, abs=1e-5)  # None: the training camera, scaled
    # a longer lens at the same size: the same pixels, depth longer by the focal ratio
    k3 = k.copy()
    k3[0, 0] *= 1.25
    k3[1, 1] *= 1.25
    longer = estimate(image, k3, weights=path)
    assert np.abs(longer.pixels - same.pixels).max() < 1e-4
    assert longer.keypoints[:, 2] == pytest.approx(1.25 * same.keypoints[:, 2], rel=1e-5)


def test_bad_input_is_named(tmp_path):
    _, path = exported(tmp_path, "multi")
    image = np.zeros((32, 32, 3))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        estimate(np.zeros((32, 32, 4)), weights=path)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        estimate(np.zeros((32, 32)), weights=path)
    with pytest.raises(TypeError, match="uint8"):
        estimate(np.zeros((32, 32, 3), np.int16), weights=path)
    bad = image.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        estimate(bad, weights=path)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        estimate(image + 2.0, weights=path)
    with pytest.raises(ValueError, match="intrinsics"):
        estimate(image, np.eye(2), weights=path)
    with pytest.raises(PoseWeightsError, match="no network"):
        estimate(image, weights=tmp_path / "missing.onnx")
    lonely = tmp_path / "lonely.onnx"
    lonely.write_bytes(path.read_bytes())
    with pytest.raises(PoseWeightsError, match="sidecar"):
        estimate(image, weights=lonely)


def test_missing_shipped_weights_say_how_to_make_them(tmp_path, monkeypatch):
    monkeypatch.setattr(inference, "DEFAULT_WEIGHTS", tmp_path / "weights" / "pose.onnx")
    with pytest.raises(PoseWeightsError, match="earcore train pose"):
        estimate(np.zeros((32, 32, 3)))


@pytest.mark.parametrize("shape", [(424, 512, 3), (424, 512), (212, 256, 3), (36, 40, 3)])
def test_whole_number_shrinks_are_block_means(shape):
    image = np.random.default_rng(0).random(shape).astype(np.float32)
    factor = 4 if shape[0] % 4 == 0 and shape[1] % 4 == 0 else 2
    h, w = shape[0] // factor, shape[1] // factor
    reference = image.reshape(h, factor, w, factor, *shape[2:]).astype(np.float64).mean(axis=(1, 3))
    got = inference.resize(image, w, h)
    assert got.shape == reference.shape and np.abs(got - reference).max() < 1e-6
