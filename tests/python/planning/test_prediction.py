"""The prediction rule for reflexes: an obstacle carried on at its velocity meets the
robot's committed motion, or not, checked against the tool's position by forward
kinematics (analytic geometry: a hand passing beside the tool's way, one heading at it)."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.planning.reflex import predicted_contact

RES = 0.02


def _hand(centre: np.ndarray, velocity) -> tuple[np.ndarray, np.ndarray]:
    """A 6 cm cube of voxels at `centre` moving at `velocity`: (voxels, velocity)."""
    g = (np.arange(3) - 1) * RES
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + centre
    return cube, np.asarray(velocity, float)


@pytest.fixture
def motion(ur5):
    """The tool moving 0.3 m along y over the horizon (committed joint states) and where
    it goes."""
    q0 = np.array([0.0, -1.6, 1.6, -1.57, -1.57, 0.0])
    tool0 = ur5.fk(q0)[-1, :3, 3]
    qs = [q0]
    from earcore.planning.ik import solve_ik

    for k in range(1, 7):
        target = ur5.fk(q0)[-1].copy()
        target[:3, 3] = tool0 + [0.0, 0.05 * k, 0.0]
        qs.append(solve_ik(ur5, target, seed_q=qs[-1], position_tolerance=1e-4, orientation_tolerance=1e-3).q)
    qs = np.array(qs)
    return qs, ur5.fk(qs)[:, -1, :3, 3]


def test_a_hand_passing_beside_the_way_does_not_fire(ur5, motion):
    qs, tools = motion
    # 20 cm beside the tool's way (along x), moving parallel to it
    hand = _hand(tools[0] + [0.20, 0.0, 0.0], [0.0, 1.6, 0.0])
    assert not predicted_contact(ur5, *hand, qs, horizon=0.3, voxel_size=RES, margin=0.05)


def test_a_hand_heading_for_the_tool_fires(ur5, motion):
    qs, tools = motion
    # 25 cm from where the tool goes, coming at 1.6 m/s: 0.48 m in the horizon
    start = tools[3] + [0.25, 0.0, 0.0]
    assert predicted_contact(ur5, *_hand(start, [-1.6, 0.0, 0.0]), qs, horizon=0.3, voxel_size=RES, margin=0.05)
    # the same hand moving away does not
    assert not predicted_contact(ur5, *_hand(start, [1.6, 0.0, 0.0]), qs, horizon=0.3, voxel_size=RES, margin=0.05)
    # nor one too far to arrive within the horizon (0.8 m away: 0.48 m travelled)
    far = tools[3] + [0.80, 0.0, 0.0]
    assert not predicted_contact(ur5, *_hand(far, [-1.6, 0.0, 0.0]), qs, horizon=0.3, voxel_size=RES, margin=0.05)


def test_no_obstacle_no_contact(ur5, motion):
    qs, _ = motion
    assert not predicted_contact(ur5, np.zeros((0, 3)), np.ones(3), qs, horizon=0.3, voxel_size=RES)
