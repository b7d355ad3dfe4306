"""Fixtures of the planning tests."""

from __future__ import annotations

import pytest

import earcore


@pytest.fixture(scope="module")
def ur5():
    return earcore.robots.load("ur5")
