"""The training entry point end to end on a small synthetic set: a run folder with its
config, checkpoint, metrics and results; the trained network reloaded, exported and
used through estimate(); the training modules import without the compiled core."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from earcore.learning.config import TrainConfig, load_config
from earcore.pose.train import load_trained, run

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402

PYTHON_TREE = Path(__import__("earcore").__file__).resolve().parent.parent


def test_train_evaluate_export(tmp_path):
    pytest.importorskip("onnxruntime")
    train_set, test_set = FakeDataset(24, 32, 32, keypoints=4, seed=0, noise=True), FakeDataset(6, 32, 32, keypoints=4, seed=1)
    config = TrainConfig(
        network="keypoint",
        steps=12,
        minutes=None,
        batch_size=8,
        log_every=2,
        eval_every_steps=6,
        eval_every_minutes=None,
        threads=1,
        network_options={"width": 0.25, "head": 16},
    )
    out = tmp_path / "run"
    result, table = run(config, Path("unused"), out, datasets=(train_set, test_set), progress=False)
    assert result.steps == 12 and len(result.evaluations) == 2
    assert load_config(out / "config.json").network_options["input_size"] == [32, 32]
    assert table is not None and set(table.metrics) == {"red", "green", "all"}
    assert "Joint error" in (out / "results.md").read_text()
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert {r["kind"] for r in records} == {"train", "eval"} and all("joints" in r for r in records if r["kind"] == "train")

    net, meta = load_trained(out)
    assert meta["robots"] == ["red", "green"] and meta["network"] == "keypoint"
    assert torch.allclose(net.intrinsics(), torch.as_tensor(train_set.intrinsics, dtype=torch.float32))

    from earcore.app.pose import export_main
    from earcore.pose import estimate

    for bad in ("0", "-1", "nan"):  # a parity check that cannot pass, or is switched off
        with pytest.raises(SystemExit):
            export_main(["pose", "--checkpoint", str(out), "--out", str(tmp_path / "bad.onnx"), "--tolerance", bad])
    assert not (tmp_path / "bad.onnx").exists()
    assert export_main(["pose", "--checkpoint", str(out), "--out", str(tmp_path / "pose.onnx")]) == 0
    image = test_set[0]["image"].numpy().transpose(1, 2, 0)
    with torch.no_grad():
        expected = net(test_set[0]["image"][None])
    found = estimate(image, train_set.intrinsics, weights=tmp_path / "pose.onnx")
    assert np.abs(found.base - expected["base"][0].numpy()).max() < 1e-4
    # where each keypoint sits travels from the manifest to the sidecar, for refine(..., frames=...)
    sidecar = json.loads((tmp_path / "pose.json").read_text())
    assert sidecar["keypoint_frames"] == train_set.manifest["keypoint_frames"]
    assert found.robot is not None and found.keypoint_frames == train_set.manifest["keypoint_frames"][found.robot]


def test_an_unknown_target_or_bad_option_is_one_line(capsys):
    from earcore.app.pose import evaluate_main, train_main

    assert train_main(["robots"]) == 2
    assert "unknown target 'robots'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        train_main(["pose", "--data", "d", "--out", "o", "--option", "width"])
    assert exit_info.value.code == 2
    assert "KEY=VALUE" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate_main(["pose", "--data", "d"])


def test_training_imports_without_the_compiled_core(tmp_path):
    """What the GPU machine runs: the package from source, no earcore._earcore."""
    tree = tmp_path / "python"
    shutil.copytree(PYTHON_TREE / "earcore", tree / "earcore", ignore=shutil.ignore_patterns("_earcore*.so", "_earcore*.pyd", "__pycache__"))
    code = (
        "import sys, earcore.pose.train, earcore.learning.train, earcore.pose.networks, earcore.pose.evaluate, earcore.pose.export;"
        "assert 'earcore._earcore' not in sys.modules;"
        "from earcore.pose.train import main; main(['--help'])"
    )
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "--network" in done.stdout
