"""Review: a batch larger than the training set is filled by repeating the set
(`EpochSampler.epoch_indices`), however large: `earcore train pose --batch 100000` on a
6-image set builds 100,000-image batches (16 GB at 128x106) and runs out of memory or
hangs, where a one-line error (or a batch capped at the set) was due."""

from __future__ import annotations

import pytest

pytest.importorskip("torch")

from earcore.learning.distributed import EpochSampler  # noqa: E402


def test_a_batch_far_larger_than_the_set_is_refused():
    with pytest.raises(ValueError, match="batch"):
        EpochSampler(6, 100_000, seed=0)
