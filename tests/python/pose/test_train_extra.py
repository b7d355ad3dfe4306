"""Training on a recordings set plus every image of other sets (`--extra`): the network's
output statistics come from the union, the run says what it was trained on, and a set
whose robots come in another order is united with it by name."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from earcore.learning.config import TrainConfig  # noqa: E402
from earcore.learning.dataset import ImageDataset  # noqa: E402
from earcore.pose.train import load_trained, run  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "learning"))
from format_folder import write_folder  # noqa: E402


def config() -> TrainConfig:
    options = {"width": 0.25, "fc": 16, "head": 8}
    return TrainConfig(network="multi", steps=2, minutes=None, batch_size=4, eval_every_steps=None, eval_every_minutes=None, threads=1, network_options=options)


def test_extra_images_join_the_training_set(tmp_path):
    main = write_folder(tmp_path / "main", robots=("ur3", "ur10"), per_robot=6, seed=0)
    extra = write_folder(tmp_path / "extra", robots=("ur3", "ur10"), per_robot=5, seed=1)
    out = tmp_path / "run"
    run(config(), main, out, extra=[extra], progress=False)
    net, meta = load_trained(out)
    assert meta["extra"] == [str(extra)]
    # Every training keypoint and base, read set by set: the train split of one, all of the other.
    points = []
    for data in (ImageDataset(main, split="train", noise=False), ImageDataset(extra, split=None, noise=False)):
        for i in range(len(data)):
            item = data[i]
            points += [item["keypoints"][item["keypoint_valid"]].numpy(), item["base"][None].numpy()]
    p = np.concatenate(points).astype(np.float64)
    assert np.allclose(net.out_mean.numpy(), p.mean(0), atol=1e-5)
    alone = np.concatenate(points[: 2 * len(ImageDataset(main, split="train"))])
    assert not np.allclose(net.out_mean.numpy(), alone.mean(0), atol=1e-5)


def test_extra_images_of_robots_in_another_order_are_united_by_name(tmp_path):
    from earcore.learning.dataset import ImageDatasets

    main = write_folder(tmp_path / "main", robots=("ur3", "ur10"), per_robot=4)
    other = write_folder(tmp_path / "other", robots=("ur10", "ur3"), per_robot=4)
    both = ImageDatasets([ImageDataset(main, split=None, noise=False), ImageDataset(other, split=None, noise=False)])
    theirs = ImageDataset(other, split=None, noise=False)
    for i in range(len(theirs)):
        assert both.robots[int(both[8 + i]["robot"])] == theirs.robots[int(theirs[i]["robot"])]
    run(config(), main, tmp_path / "run", extra=[other], progress=False)
    _, meta = load_trained(tmp_path / "run")
    assert meta["robots"] == ["ur3", "ur10"]
