"""Fixtures every test directory shares."""

from __future__ import annotations

import pytest


@pytest.fixture
def octomap():
    """The reference implementation, skipped cleanly if it is not installed."""
    return pytest.importorskip("pyoctomap")
