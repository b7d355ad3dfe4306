"""Networks that look twice (`zoom`): the zoomed training items against projecting their
3D labels and against block means; depth following the box's focal length; the two
looks' plumbing against an oracle network; estimate() (onnxruntime, numpy) against the
torch path on the same image."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from earcore.errors import ConfigError
from earcore.learning.crops import Box, crop_labels
from earcore.learning.dataset import ZoomedImages
from earcore.pose.networks import NetworkOptions, build_network
from earcore.pose.zoom import two_looks

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402


def project(k, points):
    return np.stack([k[0, 0] * points[:, 0] / points[:, 2] + k[0, 2], k[1, 1] * points[:, 1] / points[:, 2] + k[1, 2]], 1)


def test_zoomed_items_keep_their_geometry():
    data = FakeDataset(12, 64, 64, keypoints=4, seed=2)
    zoomed = ZoomedImages(data, 2, whole=0.0, seed=1)
    assert zoomed.image_size == (32, 32) and len(zoomed) == 12
    for i in range(12):
        item, source = zoomed[i], data[i]
        k = item["intrinsics"].numpy().astype(np.float64)
        valid = item["keypoint_valid"].numpy()
        expected = project(k, item["keypoints"].numpy().astype(np.float64)[valid])
        assert np.allclose(item["pixels"].numpy()[valid], expected, atol=1e-3)
        assert torch.equal(item["keypoints"], source["keypoints"]) and torch.equal(item["base"], source["base"])
        assert item["image"].shape == (3, 32, 32) and torch.equal(item["mask"][0] > 0.5, item["links"] > 0)
        # never sharper than the source: the box is at least 32 source pixels wide
        assert k[0, 0] <= data.intrinsics[0, 0] + 1e-6
    # the same item twice: the same box; another epoch: another
    assert torch.equal(zoomed[3]["image"], zoomed[3]["image"])
    first = zoomed[3]["intrinsics"].clone()
    zoomed.set_epoch(1)
    assert not torch.equal(zoomed[3]["intrinsics"], first)


def test_the_whole_image_is_its_block_means():
    data = FakeDataset(2, 64, 64, keypoints=4, seed=0)
    item = ZoomedImages(data, 2, whole=1.0)[1]
    source = data[1]["image"].numpy()
    assert np.allclose(item["image"].numpy(), source.reshape(3, 32, 2, 32, 2).mean((2, 4)), atol=1e-6)
    assert torch.equal(item["links"], torch.from_numpy(crop_labels(data[1]["links"].numpy(), Box.whole(64, 64), (32, 32))))
    with pytest.raises(ValueError, match="zoom"):
        ZoomedImages(data, 3)


def test_depth_follows_the_focal_length_only_when_zooming():
    torch.manual_seed(0)
    options = {"input_size": (32, 32), "num_keypoints": 3, "num_robots": 2, "width": 0.25, "head": 8}
    image = torch.rand(1, 3, 32, 32)
    for zoom, factor in ((2, 2.0), (1, 1.0)):
        net = build_network("keypoint", {**options, "zoom": zoom}).eval()
        k = net.intrinsics()[None]
        wide = k.clone()
        wide[:, 0, 0] *= 2
        wide[:, 1, 1] *= 2
        with torch.no_grad():
            a, b = net(image, None, k)["keypoints"][..., 2], net(image, None, wide)["keypoints"][..., 2]
        assert torch.allclose(b, factor * a, rtol=1e-5)
    with pytest.raises(ConfigError, match="keypoint network"):
        build_network("multi", {**options, "zoom": 2})
    with pytest.raises(ConfigError, match="keypoint network"):
        build_network("cascade", NetworkOptions(**{**options, "zoom": 2}))


class Oracle(torch.nn.Module):
    """Sees nothing: answers each image's true keypoints (the same for every image) as a
    perfect network would, pixels through the intrinsics it is given."""

    def __init__(self, points):
        super().__init__()
        self.options = NetworkOptions(input_size=(32, 24), num_keypoints=len(points) - 1, zoom=2)
        self.points = torch.as_tensor(points, dtype=torch.float32)
        self.calls = []

    def forward(self, image, mask=None, intrinsics=None):
        self.calls.append((image.shape, intrinsics.clone()))
        p = self.points[None].expand(image.shape[0], -1, -1)
        k = intrinsics
        uv = torch.stack([k[:, 0, 0:1] * p[..., 0] / p[..., 2] + k[:, 0, 2:3], k[:, 1, 1:2] * p[..., 1] / p[..., 2] + k[:, 1, 2:3]], -1)
        n = image.shape[0]
        return {"mask_logits": torch.zeros(n, 1, 24, 32), "keypoints": p[:, :-1], "base": p[:, -1], "pixels": uv, "type_logits": torch.zeros(n, 2)}


def test_the_second_look_is_a_sharper_box_around_the_first_answer():
    points = np.array([[0.05, 0.02, 2.0], [0.1, -0.05, 2.1], [0.12, -0.1, 2.2], [0.0, 0.1, 2.0]])
    k = torch.tensor([[[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]]])
    oracle = Oracle(points)
    out = two_looks(oracle, torch.rand(1, 3, 48, 64), k)
    (shape1, k1), (shape2, k2) = oracle.calls
    assert shape1 == shape2 == (1, 3, 24, 32)
    assert torch.allclose(k1[0, 0, 0], torch.tensor(30.0)) and k2[0, 0, 0] > 30.0 + 1e-3  # the second look is zoomed
    assert k2[0, 0, 0] <= 60.0 + 1e-4  # ... at most to the source's resolution
    # back in the image: where the points project through its own intrinsics
    assert np.allclose(out["pixels"][0].numpy(), project(k[0].numpy().astype(np.float64), points), atol=1e-3)
    assert out["mask_logits"].shape == (1, 1, 48, 64)
    box = out["boxes"][0]
    assert box.width >= 32.0 - 1e-9


def test_estimate_looks_twice_like_the_torch_path(tmp_path):
    pytest.importorskip("onnxruntime")
    from earcore.pose import estimate
    from earcore.pose.export import export_network

    torch.manual_seed(3)
    net = build_network("keypoint", {"input_size": (32, 32), "num_keypoints": 4, "num_robots": 2, "width": 0.25, "head": 16, "zoom": 2})
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    data = FakeDataset(2, 64, 64, keypoints=4, seed=5)
    net.set_output_statistics(torch.tensor([0.0, -0.1, 2.0]), torch.tensor([0.3, 0.3, 0.4]))
    net.set_camera(torch.as_tensor(data.intrinsics * np.array([[0.5], [0.5], [1.0]]), dtype=torch.float32))
    net.eval()
    export_network(net, {"robots": data.robots, "keypoints": data.manifest["keypoints"]}, tmp_path / "zoom.onnx")
    item = data[1]
    k = torch.as_tensor(data.intrinsics, dtype=torch.float32)[None]
    with torch.no_grad():
        expected = two_looks(net, item["image"][None], k)
    found = estimate(item["image"].numpy().transpose(1, 2, 0), data.intrinsics, weights=tmp_path / "zoom.onnx")
    n = len(found.keypoints)
    assert np.abs(found.pixels - expected["pixels"][0, :n].numpy()).max() < 1e-3
    assert np.abs(found.keypoints - expected["keypoints"][0, :n].numpy()).max() < 1e-4
    assert np.abs(found.base - expected["base"][0].numpy()).max() < 1e-4
    assert np.array_equal(found.mask, (expected["mask_logits"][0, 0] > 0).numpy())


def test_a_zoom_run_trains_evaluates_and_exports(tmp_path):
    from earcore.learning.config import TrainConfig
    from earcore.pose.train import load_trained, run

    config = TrainConfig(
        network="keypoint",
        steps=4,
        minutes=None,
        batch_size=8,
        eval_every_steps=None,
        eval_every_minutes=None,
        threads=1,
        network_options={"width": 0.25, "head": 16, "zoom": 2},
    )
    data = (FakeDataset(16, 64, 64, keypoints=4, seed=0, noise=True), FakeDataset(4, 64, 64, keypoints=4, seed=1))
    result, table = run(config, Path("unused"), tmp_path / "run", datasets=data, progress=False)
    net, meta = load_trained(tmp_path / "run")
    assert net.options.zoom == 2 and net.options.input_size == (32, 32) and meta["input_size"] == [32, 32]
    assert table is not None and table.metrics["all"]["samples"] == 4
    # The network's camera is the whole image's shrunk to the input (what estimate scales to
    # an image when given no camera), not a zoomed box's: fx / 2, (cx + 0.5) / 2 - 0.5.
    k = data[0].intrinsics
    expected = [[k[0, 0] / 2, 0.0, (k[0, 2] + 0.5) / 2 - 0.5], [0.0, k[1, 1] / 2, (k[1, 2] + 0.5) / 2 - 0.5], [0.0, 0.0, 1.0]]
    assert np.allclose(net.intrinsics().numpy(), expected, atol=1e-4)
    from earcore.pose.evaluate import evaluate

    assert evaluate(net, data[1], refined=False, timing=False).metrics["all"]["samples"] == 4


def test_keypoints_behind_the_camera_do_not_frame_the_box():
    data = FakeDataset(4, 64, 64, keypoints=4, seed=2)
    sample = data.samples[1]
    sample["keypoints"][0, 2] = -0.05
    sample["pixels"][0] = [5000.0, -3000.0]
    zoomed = ZoomedImages(data, 2, whole=0.0, jitter=0.0, seed=0)
    box = zoomed.box(data[1], np.random.default_rng(0))
    assert box.width <= 64.0 + 1e-9
    assert zoomed[1]["mask"].sum() > 0


def test_padding_keypoints_of_a_smaller_robot_do_not_widen_the_second_look():
    points = np.array([[0.05, 0.02, 2.0], [0.1, -0.05, 2.1], [3.0, 2.5, 2.2], [0.0, 0.1, 2.0]])  # the third: padding, far off
    k = torch.tensor([[[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]]])
    wide = two_looks(Oracle(points), torch.rand(1, 3, 48, 64), k)["boxes"][0]
    own = two_looks(Oracle(points), torch.rand(1, 3, 48, 64), k, counts=[2, 3])["boxes"][0]  # type 0 (the oracle's logits tie): 2 keypoints
    assert own.width < wide.width
    assert own == two_looks(Oracle(points[[0, 1, 3]]), torch.rand(1, 3, 48, 64), k)["boxes"][0]
