"""`earcore evaluate pose` on a dataset whose robots are not the training set's (a
held-out set of one robot, robots in another order, another arm): the dataset's robot
indices (its manifest's order) are matched by name to the network's (the type head's
classes, the checkpoint's `meta["robots"]`), so each image is reported under its own
robot and its type is counted against the network's class for that robot; a dataset
whose robots have more keypoints than the network gives is refused in one line before
anything is predicted, one with fewer is evaluated on its own; images of a robot the
network does not know are refused, or, with --other-robots, evaluated with their type
counted wrong (what a network forgot)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "learning"))
from format_folder import write_folder  # noqa: E402

from earcore.learning.checkpoint import Checkpoint, save_checkpoint  # noqa: E402
from earcore.pose.networks import build_network  # noqa: E402


def _checkpoint(folder: Path, robots: list[str], winner: int) -> Path:
    """A multi-objective network for 32x24 images whose type head always answers `winner`."""
    torch.manual_seed(0)
    net = build_network("multi", {"input_size": (32, 24), "num_keypoints": 7, "num_robots": len(robots), "width": 0.25, "fc": 16, "head": 8})
    with torch.no_grad():
        net.type_head[-1].weight.zero_()
        net.type_head[-1].bias.fill_(-10.0)
        net.type_head[-1].bias[winner] = 10.0
    meta = {"network": "multi", "options": net.options.to_dict(), "robots": robots, "keypoints": {}, "input_size": [32, 24]}
    save_checkpoint(folder / "checkpoint.pt", Checkpoint(step=1, seconds=1.0, model=net.state_dict(), config={"network": "multi"}, meta=meta))
    return folder


def test_a_one_robot_held_out_set_is_reported_under_its_own_robot(tmp_path):
    from earcore.app.pose import evaluate_main

    run = _checkpoint(tmp_path / "run", ["ur3", "ur10"], winner=1)  # always says "ur10"
    data = write_folder(tmp_path / "ur10-only", robots=("ur10",), per_robot=4, width=32, height=24)
    assert evaluate_main(["pose", "--checkpoint", str(run), "--data", str(data), "--split", "all", "--out", str(tmp_path / "out")]) == 0
    metrics = json.loads((tmp_path / "out" / "results-all.json").read_text())["metrics"]
    # every image is a UR10 and the network says UR10 for every image
    assert set(metrics) == {"ur10", "all"}, f"UR10 images reported as {sorted(metrics)}"
    assert metrics["all"]["type_accuracy"] == 1.0


def test_robots_in_another_order_keep_their_names(tmp_path):
    from earcore.app.pose import evaluate_main

    run = _checkpoint(tmp_path / "run", ["ur3", "ur10"], winner=1)
    data = write_folder(tmp_path / "swapped", robots=("ur10", "ur3"), per_robot={"ur10": 4, "ur3": 2}, width=32, height=24)
    assert evaluate_main(["pose", "--checkpoint", str(run), "--data", str(data), "--split", "all", "--out", str(tmp_path / "out")]) == 0
    metrics = json.loads((tmp_path / "out" / "results-all.json").read_text())["metrics"]
    assert metrics["ur10"]["samples"] == 4 and metrics["ur3"]["samples"] == 2, {k: v["samples"] for k, v in metrics.items()}
    # the network always says UR10: right for the 4 UR10 images, wrong for the 2 UR3s
    assert metrics["ur10"]["type_accuracy"] == 1.0 and metrics["ur3"]["type_accuracy"] == 0.0
    assert abs(metrics["all"]["type_accuracy"] - 4 / 6) < 1e-9


def test_a_set_with_another_keypoint_count_is_refused_clearly(tmp_path, capsys):
    from earcore.app.pose import evaluate_main

    run = _checkpoint(tmp_path / "run", ["ur3", "ur10"], winner=0)
    data = write_folder(tmp_path / "iiwa", robots=("iiwa",), per_robot=2, width=32, height=24)  # 8 keypoints, the network 7
    try:
        code = evaluate_main(["pose", "--checkpoint", str(run), "--data", str(data), "--split", "all", "--out", str(tmp_path / "out")])
    except ValueError as exc:  # numpy's "operands could not be broadcast together ..." is not a clear error
        pytest.fail(f"not a clear error: {exc}")
    err = capsys.readouterr().err
    assert code != 0 and "keypoint" in err and "broadcast" not in err, err


def test_fewer_keypoints_and_robots_the_network_does_not_know(tmp_path, capsys):
    from earcore.app.pose import evaluate_main

    torch.manual_seed(0)
    net = build_network("multi", {"input_size": (32, 24), "num_keypoints": 8, "num_robots": 1, "width": 0.25, "fc": 16, "head": 8})
    meta = {"network": "multi", "options": net.options.to_dict(), "robots": ["iiwa"], "keypoints": {}, "input_size": [32, 24]}
    run = tmp_path / "iiwa-run"
    save_checkpoint(run / "checkpoint.pt", Checkpoint(step=1, seconds=1.0, model=net.state_dict(), config={"network": "multi"}, meta=meta))
    data = write_folder(tmp_path / "ur", robots=("ur3", "ur10"), per_robot=2, width=32, height=24)  # 7 keypoints, the network 8
    args = ["pose", "--checkpoint", str(run), "--data", str(data), "--split", "all", "--out", str(tmp_path / "out")]
    assert evaluate_main(args) != 0
    assert "not ur3, ur10" in capsys.readouterr().err
    assert evaluate_main([*args, "--other-robots"]) == 0
    metrics = json.loads((tmp_path / "out" / "results-all.json").read_text())["metrics"]
    assert metrics["ur3"]["samples"] == 2 and metrics["ur10"]["samples"] == 2
    assert metrics["all"]["type_accuracy"] == 0.0
    # the joint error over the 7 keypoints the data has, by hand from the predictions
    from earcore.learning.dataset import ImageDataset
    from earcore.pose.evaluate import predict

    p = predict(net.eval(), ImageDataset(data, split=None, noise=False), torch.device("cpu"))
    d = np.linalg.norm(p["keypoints"][:, :7] - p["keypoints_true"], axis=-1)
    per_image = (d * p["valid"]).sum(1) / p["valid"].sum(1)
    assert metrics["all"]["joints_mean_cm"] == pytest.approx(100 * per_image.mean(), rel=1e-5)
