"""Transfer learning for the pose networks: what is copied, adapted and left fresh;
frozen parameters (and their batch-norm statistics) bit-identical after training;
a transfer run from a checkpoint file resumes to the same weights as one that was
never interrupted; learned loss weighting through the training entry point."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402

from earcore.errors import ConfigError  # noqa: E402
from earcore.learning.checkpoint import load_checkpoint  # noqa: E402
from earcore.learning.config import TrainConfig  # noqa: E402
from earcore.learning.freeze import freeze  # noqa: E402
from earcore.pose.networks import build_network  # noqa: E402
from earcore.pose.train import run  # noqa: E402
from earcore.pose.transfer import trainable_modules, transfer_weights  # noqa: E402

OPTIONS = {"width": 0.25, "fc": 16, "head": 8}


def _config(**changes) -> TrainConfig:
    base = {
        "network": "multi",
        "steps": 3,
        "minutes": None,
        "batch_size": 4,
        "threads": 1,
        "eval_every_minutes": None,
        "weight_decay": 1e-3,
        "network_options": dict(OPTIONS),
    }
    return TrainConfig(**{**base, **changes})


class Renamed(FakeDataset):
    """The fake set under other robot names and another keypoint count."""

    def __init__(self, robots: list[str], *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.robots = list(robots)
        self.manifest = {**self.manifest, "robots": self.robots}


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A multi network trained a few steps on robots "red" and "green" with 4 keypoints."""
    out = tmp_path_factory.mktemp("source") / "run"
    run(_config(), Path("unused"), out, datasets=(FakeDataset(8, 32, 32, keypoints=4, seed=0), FakeDataset(2, 32, 32, keypoints=4, seed=1)), progress=False)
    return out


def test_output_rows_follow_robot_names_and_keypoint_indices(source):
    state = load_checkpoint(source)
    new = build_network("multi", {**OPTIONS, "input_size": (32, 32), "num_keypoints": 5, "num_robots": 2})
    fresh = {k: v.clone() for k, v in new.state_dict().items()}
    report = transfer_weights(new, state.model, state.meta, ["green", "blue"])
    got = new.state_dict()
    old = state.model
    # "green" was row 1 of the old type head and is row 0 now; "blue" keeps its fresh row
    assert torch.equal(got["type_head.2.weight"][0], old["type_head.2.weight"][1])
    assert torch.equal(got["type_head.2.bias"][0], old["type_head.2.bias"][1])
    assert torch.equal(got["type_head.2.weight"][1], fresh["type_head.2.weight"][1])
    # keypoints 1-4 keep their rows, the 5th is fresh
    assert torch.equal(got["joints_head.2.weight"][:12], old["joints_head.2.weight"])
    assert torch.equal(got["joints_head.2.weight"][12:], fresh["joints_head.2.weight"][12:])
    # everything of the same shape is copied, the output scaling included
    assert torch.equal(got["out_mean"], old["out_mean"]) and torch.equal(got["trunk.0.weight"], old["trunk.0.weight"])
    assert set(report.adapted) == {"type_head.2.weight", "type_head.2.bias", "joints_head.2.weight", "joints_head.2.bias"}
    assert "blue" in report.describe()


def test_bad_transfers_are_refused(source):
    state = load_checkpoint(source)
    other_size = build_network("multi", {**OPTIONS, "input_size": (48, 32)})
    with pytest.raises(ConfigError, match="32×32"):
        transfer_weights(other_size, state.model, state.meta, ["red", "green"])
    keypoint = build_network("keypoint", {**OPTIONS, "input_size": (32, 32)})
    with pytest.raises(ConfigError, match="multi network"):
        transfer_weights(keypoint, state.model, state.meta, ["red", "green"])
    net = build_network("multi", {**OPTIONS, "input_size": (32, 32)})
    with pytest.raises(ConfigError, match="no parameters under"):
        freeze(net, trainable_modules(net, "stage-7"))
    assert trainable_modules(net, ["dense", "mask_out", "joints_head"]) == ["blue_fc", "green_fc", "joints_head", "type_head", "base_head", "mask_out"]
    with pytest.raises(ConfigError, match="paper-vi"):
        trainable_modules(keypoint, "paper-vi")


def test_frozen_parameters_and_statistics_stay_bit_identical(source, tmp_path):
    new_set = Renamed(["green", "blue"], 8, 32, 32, keypoints=5, seed=2, noise=True)
    config = _config(transfer_from=str(source), trainable="paper-vi", steps=4)
    run(config, Path("unused"), tmp_path / "vi", datasets=(new_set, Renamed(["green", "blue"], 2, 32, 32, keypoints=5, seed=3)), progress=False)
    before, after = load_checkpoint(source).model, load_checkpoint(tmp_path / "vi").model
    net = build_network("multi", {**OPTIONS, "input_size": (32, 32), "num_keypoints": 5})
    trainable = trainable_modules(net, "paper-vi")
    assert trainable == ["blue_fc", "green_fc", "joints_head", "type_head", "base_head", "red_b.1", "mask_out"]

    def trains(key: str) -> bool:
        return any(key == p or key.startswith(p + ".") for p in trainable)

    frozen = [k for k in after if not trains(k) and before[k].shape == after[k].shape]
    assert any(k.endswith("running_mean") for k in frozen) and any(k.startswith("blue.") for k in frozen)
    changed = [k for k in frozen if not k.endswith("num_batches_tracked") and not torch.equal(before[k], after[k])]
    assert not changed, f"frozen tensors changed: {changed[:4]}"
    moved = [k for k in after if trains(k) and k.endswith("weight") and before[k].shape == after[k].shape and not torch.equal(before[k], after[k])]
    assert "blue_fc.weight" in moved and "mask_out.weight" in moved and "red_b.1.0.weight" in moved


def test_a_transfer_from_a_checkpoint_file_resumes_to_the_uninterrupted_weights(source, tmp_path):
    exported = tmp_path / "exported.pt"
    shutil.copy(source / "checkpoint.pt", exported)
    sets = (Renamed(["green", "blue"], 8, 32, 32, keypoints=5, seed=2, noise=True), Renamed(["green", "blue"], 2, 32, 32, keypoints=5, seed=3))
    whole = _config(transfer_from=str(exported), trainable="late", steps=6, schedule="constant", log_every=1, loss_combiner="auxnet", combiner_options={"warmup": 2})
    run(whole, Path("unused"), tmp_path / "whole", datasets=sets, progress=False)
    run(whole.replace(steps=3), Path("unused"), tmp_path / "parts", datasets=sets, progress=False)
    run(whole, Path("unused"), tmp_path / "parts", datasets=sets, progress=False, resume=True)
    a, b = load_checkpoint(tmp_path / "whole"), load_checkpoint(tmp_path / "parts")
    assert a.step == b.step == 6
    differ = [k for k in a.model if not torch.equal(a.model[k], b.model[k])]
    assert not differ, differ[:4]
    assert a.combiner is not None and b.combiner is not None
    assert all(torch.equal(a.combiner[k], b.combiner[k]) for k in a.combiner if isinstance(a.combiner[k], torch.Tensor))
    records = [json.loads(line) for line in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    weights = [r["w_joints"] for r in records if r["kind"] == "train"]
    assert weights[0] == 1.0 and weights[-1] != 1.0  # the plain sum during warm-up, AuxNet's after


def test_every_parameter_frozen_is_an_error(source, tmp_path):
    sets = (FakeDataset(8, 32, 32, keypoints=4, seed=0), FakeDataset(2, 32, 32, keypoints=4, seed=1))
    with pytest.raises(ConfigError, match="no parameters under"):
        run(_config(transfer_from=str(source), trainable=["nothing_here"]), Path("unused"), tmp_path / "x", datasets=sets, progress=False)


def test_a_few_images_drawn_from_the_training_set(tmp_path):
    from earcore.learning.dataset import SampledImages

    full = FakeDataset(8, 32, 32, keypoints=4, seed=0)
    a, b = SampledImages(full, 5, seed=1), SampledImages(full, 5, seed=1)
    assert len(a) == 5 and len(set(a.indices.tolist())) == 5 and a.indices.tolist() == b.indices.tolist()
    assert a.indices.tolist() != SampledImages(full, 5, seed=2).indices.tolist()
    assert a.robots == full.robots and a.image_size == (32, 32)
    assert torch.equal(a[0]["image"], full[int(a.indices[0])]["image"])
    with pytest.raises(ConfigError, match="train_samples: 9 images asked for, the set has 8"):
        run(_config(train_samples=9), Path("unused"), tmp_path / "x", datasets=(full, FakeDataset(2, 32, 32, keypoints=4, seed=1)), progress=False)


def test_patience_on_a_value_the_pose_evaluation_does_not_give_is_refused_before_training(tmp_path):
    sets = (FakeDataset(8, 32, 32, keypoints=4, seed=0), FakeDataset(2, 32, 32, keypoints=4, seed=1))
    with pytest.raises(ConfigError, match="patience_metric must be one of"):
        run(_config(patience=2), Path("unused"), tmp_path / "x", datasets=sets, progress=False)
    assert not (tmp_path / "x").exists()


def test_joined_sets_unite_robots_and_a_few_images_of_each_robot(tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "learning"))
    from format_folder import write_folder

    from earcore.learning.dataset import ImageDataset, ImageDatasets, SampledImages

    old = write_folder(tmp_path / "old", robots=("ur3", "ur10"), per_robot=10, width=32, height=24)
    new = write_folder(tmp_path / "new", robots=("iiwa",), per_robot=10, width=32, height=24, seed=1)
    both = ImageDatasets([ImageDataset(old, split=None, noise=False), ImageDataset(new, split=None, noise=False)])
    few = SampledImages(both, 3, seed=0, per_robot=True)
    labels = both.robot_labels()[few.indices]
    assert sorted(np.bincount(labels).tolist()) == [3, 3, 3]
    config = _config(train_samples=3, samples_per_robot=True, batch_size=3, network_options={**OPTIONS})
    result, table = run(config, old, tmp_path / "run", join=[new], progress=False)
    meta = load_checkpoint(tmp_path / "run").meta
    assert meta["robots"] == ["ur3", "ur10", "iiwa"] and meta["join"] == [str(new)]
    assert table is not None and {"ur3", "ur10", "iiwa"} <= set(table.metrics)


def test_robots_pick_in_the_data_and_a_joined_set_brings_all_its_robots(tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "learning"))
    from format_folder import write_folder

    new = write_folder(tmp_path / "new", robots=("ur3", "iiwa"), per_robot=6, width=32, height=24, seed=1)
    old = write_folder(tmp_path / "old", robots=("ur3", "ur10"), per_robot=6, width=32, height=24)
    config = _config(steps=1, batch_size=4)
    _, table = run(config, new, tmp_path / "run", robots=["iiwa"], join=[old], progress=False)
    assert table is not None
    shown = {r: int(m["samples"]) for r, m in table.metrics.items() if r != "all"}
    assert set(shown) == {"iiwa", "ur3", "ur10"} and shown["ur3"] > 0 and shown["ur10"] > 0, shown
