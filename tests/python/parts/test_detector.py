"""The parts dataset's items against its labels, a tiny detector overfitting one batch,
picking by weighted k-means, and the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from earcore.learning.losses import centroid_distance, soft_iou_error
from earcore.learning.train import collate
from earcore.parts.detector import build_detector
from earcore.parts.pickup import pickup_points, weighted_kmeans

pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from earcore.app.parts import main

    folder = tmp_path_factory.mktemp("parts") / "data"
    assert main(["generate", "--out", str(folder), "--count", "24", "--size", "64x48", "--workers", "1", "--quiet", "--seed", "3"]) == 0
    return folder


def test_items_match_the_labels(data):
    from earcore.learning.shards import read_manifest, read_shard
    from earcore.parts.dataset import PartImages, depth_channel

    items = PartImages(data, split=None, noise=False)
    manifest = read_manifest(data)
    shard = read_shard(data, "shard-00000", 64, 48, layers=manifest["layers"])
    assert len(items) == 24
    for k in range(5):
        item = items[k]
        count = int(shard.text["count"][k])
        assert int(item["valid"].sum()) == count
        inst = shard.images["instances"][k]
        for i in range(count):
            cls = int(shard.text[f"obj{i}_class"][k])
            assert int(item["classes"][i]) == cls
            assert item["points"][i].tolist() == pytest.approx([float(shard.text[f"obj{i}_u"][k]), float(shard.text[f"obj{i}_v"][k])], abs=1e-4)
            # the class target holds the instance's pixels
            assert bool(item["target"][cls][torch.from_numpy(inst == i + 1)].all())
        assert int(item["target"].sum()) == int((inst > 0).sum())  # one class per part pixel
        assert torch.equal(item["image"][:3], torch.from_numpy(shard.images["rgb"][k].transpose(2, 0, 1).astype(np.float32) / 255))
        assert torch.equal(item["image"][3], torch.from_numpy(depth_channel(shard.images["depth"][k])))
        assert item["counts"].tolist() == np.bincount([int(shard.text[f"obj{i}_class"][k]) for i in range(count)], minlength=13).tolist()


def test_depth_channel_is_height_above_the_platform():
    from earcore.parts.dataset import DEPTH_SCALE, depth_channel

    d = np.full((6, 8), 500, dtype=np.uint16)
    d[2, 3] = 480  # 2 cm above the platform
    d[0, 0] = 0  # no return
    out = depth_channel(d)
    assert out[2, 3] == pytest.approx(0.02 / DEPTH_SCALE) and out[0, 0] == 0 and out[5, 5] == 0


def test_a_tiny_detector_overfits_one_batch(data):
    from earcore.parts.dataset import PartImages

    torch.manual_seed(0)
    batch = collate([PartImages(data, split=None, noise=False)[i] for i in range(4)])
    net = build_detector(13, 64, 48, widths=(8, 16, 32, 32), dropout=0.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = None
    for _ in range(300):
        a = net(batch["image"])["activations"]
        iou = soft_iou_error(a, batch["target"])
        dist = centroid_distance(a, batch["points"], batch["classes"], batch["valid"])
        first = first or (float(iou.detach()), float(dist.detach()))
        opt.zero_grad()
        (iou + 0.05 * dist).backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        a = net(batch["image"])["activations"]
        iou, dist = float(soft_iou_error(a, batch["target"])), float(centroid_distance(a, batch["points"], batch["classes"], batch["valid"]))
    assert first[0] > 0.99 and iou < 0.65, (first, iou)
    assert dist < 1.5 and dist < first[1] / 4, (first, dist)


def test_weighted_kmeans_and_picks_on_blobs():
    h, w = 40, 60
    v, u = np.mgrid[0:h, 0:w]
    act = np.zeros((2, h, w))
    centres = [(10.0, 10.0), (45.0, 30.0), (30.0, 8.0)]
    for cu, cv in centres:  # three round blobs of class 0
        act[0] += np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / 4.0)
    act[1] = np.exp(-(((u - 30) / 8.0) ** 2 + ((v - 25) / 2.0) ** 2))  # an elongated blob along u
    picks = pickup_points(act, [3, 1])
    found = sorted((round(p.u), round(p.v)) for p in picks if p.cls == 0)
    assert found == sorted((round(a), round(b)) for a, b in centres)
    bar = next(p for p in picks if p.cls == 1)
    assert (bar.u, bar.v) == pytest.approx((30, 25), abs=1e-4)
    assert abs(np.sin(bar.axis)) < 1e-6  # its dominant axis is the image's u axis
    labels = weighted_kmeans(np.array([[0.0, 0], [1, 0], [10, 0], [11, 0]]), np.ones(4), 2)
    assert labels[0] == labels[1] != labels[2] == labels[3]


def test_train_and_evaluate_commands(data, tmp_path, capsys):
    from earcore.app.parts import main

    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "4", "--batch", "4", "--option", "widths=[4,8,8,8]", "--no-progress"]) == 0
    results = json.loads((run / "results.json").read_text())
    assert results["all"]["parts"] > 0 and 0 <= results["all"]["pickup_rate"] <= 1
    assert main(["evaluate", "--checkpoint", str(run), "--data", str(data), "--limit", "3", "--out", str(tmp_path / "ev")]) == 0
    assert json.loads((tmp_path / "ev" / "results.json").read_text())["images"] == 3
    # resuming the same run with more steps continues it; bad weights are refused
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "6", "--batch", "4", "--option", "widths=[4,8,8,8]", "--resume", "--no-progress"]) == 0
    with pytest.raises(SystemExit):
        main(["train", "--data", str(data), "--out", str(tmp_path / "r2"), "--weights", "iou=1", "--steps", "1"])
    assert main(["evaluate", "--checkpoint", str(tmp_path / "nothing"), "--data", str(data)]) == 1
    # Images of another size: refused with both sizes, not a tensor-size traceback.
    small = tmp_path / "small"
    assert main(["generate", "--out", str(small), "--count", "2", "--size", "32x24", "--workers", "1", "--quiet", "--seed", "3"]) == 0
    assert main(["evaluate", "--checkpoint", str(run), "--data", str(small)]) == 2
    assert "32×24 images, the detector takes 64×48" in capsys.readouterr().err
