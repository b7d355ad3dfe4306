"""A batch larger than the training set is refused with a one-line `ConfigError` naming
both sizes (rather than filling the batch by repeating the set: `--batch 100000` on a
6-image set would build 100,000-image batches and run out of memory)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).parent))
from tiny import TinyNet, TinyObjective, TinySet  # noqa: E402

from earcore.errors import ConfigError  # noqa: E402
from earcore.learning.combiners import FixedWeights  # noqa: E402
from earcore.learning.config import TrainConfig  # noqa: E402
from earcore.learning.distributed import EpochSampler  # noqa: E402
from earcore.learning.train import train  # noqa: E402


def test_a_batch_far_larger_than_the_set_is_refused():
    with pytest.raises(ValueError, match="batch"):
        EpochSampler(6, 100_000, seed=0)


def test_a_batch_of_the_whole_set_is_one_batch_per_epoch():
    sampler = EpochSampler(6, 6, seed=0)
    assert sampler.per_epoch == 1 and sorted(sampler.epoch_indices(0)) == list(range(6))


def test_training_with_a_batch_larger_than_the_set_names_both_sizes(tmp_path):
    config = TrainConfig(network="multi", steps=1, minutes=None, batch_size=32, threads=1, eval_every_minutes=None)
    with pytest.raises(ConfigError, match=r"batch_size 32 .*\(24 samples\)") as caught:
        train(TinyNet(), TinyObjective(), TinySet(24), config, tmp_path / "run", combiner=FixedWeights({"joints": 1.0}), log=None, progress=False)
    assert len(str(caught.value).splitlines()) == 1
