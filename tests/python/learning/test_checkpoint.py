"""A run interrupted and resumed ends with the parameters of the uninterrupted run."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from earcore.errors import ConfigError
from earcore.learning.checkpoint import CheckpointError, load_checkpoint
from earcore.learning.combiners import FixedWeights
from earcore.learning.config import TrainConfig
from earcore.learning.metrics_log import read_metrics
from earcore.learning.train import train

sys.path.insert(0, str(Path(__file__).parent))
from tiny import TinyNet, TinyObjective, TinySet  # noqa: E402

CONFIG = TrainConfig(
    network="tiny", steps=10, minutes=None, batch_size=8, lr_start=1e-2, lr_end=1e-4, log_every=1, eval_every_steps=4, eval_every_minutes=None, threads=1
)


def run(folder, objective, resume=False):
    torch.manual_seed(0)
    model = TinyNet()
    result = train(
        model, objective, TinySet(), CONFIG, folder, combiner=FixedWeights({"joints": 1.0}), val_set=TinySet(8, seed=1), resume=resume, progress=False, log=None
    )
    return model, result


def test_resume_reproduces_the_uninterrupted_run(tmp_path):
    whole, result = run(tmp_path / "whole", TinyObjective())
    assert result.steps == 10
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "split", TinyObjective(interrupt_at=8))  # 6 steps done (the evaluation at step 4 asks for inputs once)
    assert load_checkpoint(tmp_path / "split").step == 6
    resumed, result = run(tmp_path / "split", TinyObjective(), resume=True)
    assert result.steps == 10
    for (name, a), b in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name

    # the same training records, the resumed ones appended
    def train_losses(folder):
        return [(r["step"], r["joints"]) for r in read_metrics(folder / "metrics.jsonl") if r["kind"] == "train"]

    assert train_losses(tmp_path / "whole") == train_losses(tmp_path / "split")
    # an ordinary restart is not a resume: the drop-out draws differ, so the parameters too
    other = TinyNet()
    torch.manual_seed(0)
    assert not all(torch.equal(a, b) for a, b in zip(whole.state_dict().values(), other.state_dict().values()))


def test_an_existing_run_is_not_overwritten_and_bad_checkpoints_are_named(tmp_path):
    run(tmp_path / "a", TinyObjective())
    with pytest.raises(ConfigError, match="already holds a run"):
        run(tmp_path / "a", TinyObjective())
    bad = tmp_path / "b" / "checkpoint.pt"
    bad.parent.mkdir()
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="checkpoint.pt"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing")


def test_resume_after_a_crash_logs_each_step_once(tmp_path):
    """A run killed after its last checkpoint has logged steps the resumed run does
    again: resuming drops the records after the checkpoint's step, so metrics.jsonl holds
    each step once, as the uninterrupted run's does."""
    run(tmp_path / "whole", TinyObjective())
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "split", TinyObjective(interrupt_at=8))
    assert load_checkpoint(tmp_path / "split").step == 6
    log = tmp_path / "split" / "metrics.jsonl"
    lost = [json.dumps({"kind": "train", "step": s, "seconds": 0.1 * s, "time": 0.0, "joints": 9.9}) for s in (7, 8)]
    with log.open("a") as f:  # what a run killed at step 8 (its checkpoint at 6) leaves, with a cut last line
        f.write("\n".join(lost) + '\n{"kind": "train", "st')
    run(tmp_path / "split", TinyObjective(), resume=True)

    def records(folder, kind):
        return [(r["step"], r.get("joints")) for r in read_metrics(folder / "metrics.jsonl") if r["kind"] == kind]

    assert records(tmp_path / "split", "train") == records(tmp_path / "whole", "train")
    evaluated = [step for step, _ in records(tmp_path / "split", "eval")]
    assert len(evaluated) == len(set(evaluated)), evaluated


def test_a_fresh_run_in_a_folder_without_a_checkpoint_starts_a_fresh_log(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "metrics.jsonl").write_text(json.dumps({"kind": "train", "step": 3, "seconds": 1.0, "time": 0.0, "joints": 9.9}) + "\n")
    run(folder, TinyObjective())
    assert all(r.get("joints") != 9.9 for r in read_metrics(folder / "metrics.jsonl"))


def test_resuming_into_another_network_shape_is_one_line(tmp_path):
    run(tmp_path / "run", TinyObjective())
    wide = TinyNet()
    wide.body[1] = torch.nn.Linear(48, 32)
    wide.body[4] = torch.nn.Linear(32, 6)
    later = CONFIG.replace(steps=12)
    with pytest.raises(CheckpointError, match="another network shape") as caught:
        train(wide, TinyObjective(), TinySet(), later, tmp_path / "run", combiner=FixedWeights({"joints": 1.0}), resume=True, progress=False, log=None)
    assert len(str(caught.value).splitlines()) == 1
