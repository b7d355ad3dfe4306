"""Early stopping (`patience`): the run stops after that many evaluations without a new
best value, and the count survives a checkpoint, so an interrupted run stops where an
uninterrupted one does and a run that stopped stays stopped when resumed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from tiny import TinyNet, TinyObjective, TinySet  # noqa: E402

from earcore.errors import ConfigError  # noqa: E402
from earcore.learning.checkpoint import load_checkpoint  # noqa: E402
from earcore.learning.combiners import FixedWeights  # noqa: E402
from earcore.learning.config import TrainConfig  # noqa: E402
from earcore.learning.train import train  # noqa: E402

#: evaluation k (1, 2, ...) gives this value: a best at the 2nd, nothing better after
VALUES = [5.0, 3.0, 4.0, 3.5, 3.2, 3.1, 3.0, 2.0, 1.0, 0.5]


class Scripted:
    def __init__(self):
        self.calls = 0

    def __call__(self, model, dataset, device, limit):
        self.calls += 1
        return {"score": VALUES[self.calls - 1]}


def config(steps: int) -> TrainConfig:
    return TrainConfig(
        network="tiny", steps=steps, minutes=None, batch_size=4, eval_every_steps=1, eval_every_minutes=None, patience=3, patience_metric="score", threads=1
    )


def fit(folder: Path, steps: int, evaluator: Scripted, resume: bool = False):
    return train(
        TinyNet(),
        TinyObjective(),
        TinySet(),
        config(steps),
        folder,
        combiner=FixedWeights({"joints": 1.0}),
        val_set=TinySet(4, seed=1),
        evaluate=evaluator,
        resume=resume,
        progress=False,
        log=None,
    )


def test_patience_stops_and_its_count_survives_a_resume(tmp_path):
    whole = fit(tmp_path / "whole", 10, Scripted())
    # best at evaluation 2 (step 2); evaluations 3, 4, 5 bring nothing better: stop after step 5
    assert whole.steps == 5
    scripted = Scripted()
    first = fit(tmp_path / "parts", 3, scripted)
    assert first.steps == 3 and load_checkpoint(tmp_path / "parts").patience == {"value": 3.0, "since": 1}
    resumed = fit(tmp_path / "parts", 10, scripted, resume=True)
    assert resumed.steps == 5
    again = fit(tmp_path / "parts", 10, scripted, resume=True)
    assert again.steps == 5, "a run that stopped on patience must not train on when resumed"


def test_a_metric_the_evaluation_does_not_give_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="score"):
        train(
            TinyNet(),
            TinyObjective(),
            TinySet(),
            config(4),
            tmp_path / "x",
            combiner=FixedWeights({"joints": 1.0}),
            val_set=TinySet(4, seed=1),
            progress=False,
            log=None,
        )
