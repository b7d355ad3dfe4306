"""The pose training entry point (`earcore.pose.train.run` / `main`):

- `config.seed` seeds the network's initial weights: the same configuration run twice
  in one process (as benches/pose_accuracy.py does, network after network) gives the
  same weights;
- a loss weight under a name the network's objective never produces (a typo in a
  config file) is a `ConfigError` naming the known losses;
- `--resume` with other network options (a preset, `--option width=...`, a dataset of
  another size) is a one-line `CheckpointError` naming the options that differ, not
  torch's page of "size mismatch" lines;
- `python -m earcore.pose.train` (the GPU machine's entry point) reports a missing
  dataset in one line on stderr, with no traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402

from earcore.errors import ConfigError, EarcoreError  # noqa: E402
from earcore.learning.checkpoint import load_checkpoint  # noqa: E402
from earcore.learning.config import TrainConfig  # noqa: E402
from earcore.pose.train import run  # noqa: E402

PYTHON_TREE = Path(__import__("earcore").__file__).resolve().parent.parent


def _config(**changes) -> TrainConfig:
    base = {
        "network": "multi",
        "steps": 1,
        "minutes": None,
        "batch_size": 4,
        "threads": 1,
        "eval_every_minutes": None,
        "network_options": {"width": 0.25, "fc": 16, "head": 8},
    }
    return TrainConfig(**{**base, **changes})


def _sets():
    return FakeDataset(8, 32, 32, keypoints=4, seed=0), FakeDataset(2, 32, 32, keypoints=4, seed=1)


def test_the_same_configuration_gives_the_same_weights(tmp_path):
    run(_config(), Path("unused"), tmp_path / "a", datasets=_sets(), progress=False)
    run(_config(), Path("unused"), tmp_path / "b", datasets=_sets(), progress=False)
    a, b = load_checkpoint(tmp_path / "a").model, load_checkpoint(tmp_path / "b").model
    differ = [k for k in a if not torch.equal(a[k], b[k])]
    assert not differ, f"same config, same data, other weights: {differ[:3]}"


def test_a_misspelt_loss_weight_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="joint"):
        run(_config(loss_weights={"joint": 3.0}), Path("unused"), tmp_path / "run", datasets=_sets(), progress=False)


def test_resuming_with_other_network_options_is_a_clear_error(tmp_path):
    run(_config(), Path("unused"), tmp_path / "run", datasets=_sets(), progress=False)
    wider = _config(steps=2, network_options={"width": 0.5, "fc": 16, "head": 8})
    try:
        run(wider, Path("unused"), tmp_path / "run", datasets=_sets(), resume=True, progress=False)
    except EarcoreError as exc:
        assert "width" in str(exc) or "option" in str(exc)
    except RuntimeError as exc:  # load_state_dict's "size mismatch for trunk.0.weight ..."
        pytest.fail(f"a RuntimeError of {len(str(exc).splitlines())} lines instead of a one-line error")
    else:
        pytest.fail("resumed a run with other network options")


def test_python_m_train_reports_a_missing_dataset_in_one_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(PYTHON_TREE)}
    done = subprocess.run(
        [sys.executable, "-m", "earcore.pose.train", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run"), "--steps", "1"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and "nowhere" in done.stderr, done.stderr


def test_python_m_train_reports_a_batch_larger_than_the_set_in_one_line(tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "learning"))
    from format_folder import write_folder

    data = write_folder(tmp_path / "data", robots=("ur3", "ur10"), per_robot=4, width=32, height=24)  # 4 training images
    env = {**os.environ, "PYTHONPATH": str(PYTHON_TREE)}
    done = subprocess.run(
        [sys.executable, "-m", "earcore.pose.train", "--data", str(data), "--out", str(tmp_path / "run"), "--steps", "1", "--batch", "64", "--no-progress"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "batch_size 64" in done.stderr and "4 samples" in done.stderr, done.stderr
