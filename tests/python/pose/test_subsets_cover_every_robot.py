"""Datasets hold their robots one after another (a robot per shard; `format_folder`
writes them robot-major, the worst case), so whatever reads "N images" of a set draws
them at random across the whole set (the same for the same seed), and the generator
interleaves the robots' shards:

- `fit_statistics` (the output standardisation and the camera) describes every
  robot of the training split, not the first robot's shards;
- a limited evaluation (the periodic evaluation during training, `eval_samples`)
  sees every robot;
- `plan_shards` puts a shard of each robot first, and stays deterministic."""

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
    assert first == ["ur3", "ur5", "ur10"], [s[0].robot for s in shards]
    assert all(len({spec.robot for spec in shard}) == 1 for shard in shards)  # still one robot per shard
    again = plan_shards(RobotImageOptions(robots=("ur3", "ur5", "ur10"), mode="recordings", count=40, shard_size=10))
    assert again == shards
    keys = [spec.key for shard in shards for spec in shard]
    assert len(keys) == len(set(keys)) == 120


def test_a_limited_evaluation_is_the_same_for_the_same_seed(folder):
    test = ImageDataset(folder, split="test", noise=False)
    net = build_network("multi", {"input_size": (16, 16), "num_keypoints": 7, "num_robots": 2, "width": 0.25, "fc": 8, "head": 8})
    a = predict(net, test, torch.device("cpu"), limit=20)
    b = predict(net, test, torch.device("cpu"), limit=20)
    assert len(a["robot"]) == 20 and all(np.array_equal(a[k], b[k]) for k in a)
