"""Review: datasets are stored one robot per shard, in the manifest's robot order
(`plan_shards`: "shards in shuffled order" is not what it does), and the Dataset keeps
that order. Two consumers take "the first N" images as if they were a sample of all:

- `fit_statistics` (the output standardisation and the camera) reads the first 256
  training images: on the papers' UR set (256 images per shard) that is UR3 only
  (mean depth 0.51 m against 0.78 m over the training split, spread about half);
- the periodic evaluation during training (`eval_samples`, default 512) reads the
  first 512 test images: UR3 and UR5, never a UR10, so the accuracy-vs-time curves
  leave a robot out."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "learning"))
from format_folder import write_folder  # noqa: E402

from earcore.learning.dataset import ImageDataset  # noqa: E402
from earcore.pose.evaluate import predict  # noqa: E402
from earcore.pose.networks import build_network  # noqa: E402
from earcore.pose.train import fit_statistics  # noqa: E402


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    # 300 UR3 then 100 UR10 training images, as the generator orders them (UR3's shards first)
    return write_folder(tmp_path_factory.mktemp("order"), robots=("ur3", "ur10"), per_robot={"ur3": 600, "ur10": 200}, width=16, height=16, shard_size=256)


def test_output_statistics_describe_every_robot_of_the_training_set(folder):
    train = ImageDataset(folder, split="train", noise=False)
    net = build_network("multi", {"input_size": (16, 16), "num_keypoints": 7, "num_robots": 2, "width": 0.25, "fc": 8, "head": 8})
    fit_statistics(net, train)
    points = []
    for i in range(len(train)):
        item = train[i]
        points += [item["keypoints"][item["keypoint_valid"]], item["base"][None]]
    truth = torch.cat(points).double().mean(0)
    # UR3 depths ~0.5 m, UR10 ~1.0 m: the training set's mean depth is ~0.63 m
    assert abs(float(net.out_mean[2]) - float(truth[2])) < 0.05, (float(net.out_mean[2]), float(truth[2]))


def test_a_limited_evaluation_sees_every_robot(folder):
    test = ImageDataset(folder, split="test", noise=False)
    net = build_network("multi", {"input_size": (16, 16), "num_keypoints": 7, "num_robots": 2, "width": 0.25, "fc": 8, "head": 8})
    p = predict(net, test, torch.device("cpu"), limit=len(test) // 2)
    assert set(np.unique(p["robot"]).tolist()) == {0, 1}, "the periodic evaluation left a robot out"


def test_the_generator_interleaves_the_robots_shards():
    pytest.importorskip("pybullet")
    from earcore.sim.robot_images import RobotImageOptions, plan_shards

    shards = plan_shards(RobotImageOptions(robots=("ur3", "ur5", "ur10"), mode="recordings", count=40, shard_size=10))
    first = [s[0].robot for s in shards[:3]]
    # the docstring: "shards in shuffled order"; today: ur3, ur3, ur3, ur3, ur5, ...
    assert len(set(first)) > 1, [s[0].robot for s in shards]
