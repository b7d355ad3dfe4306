"""Speed and separation monitoring in the executive (`Executive.ssm_scale`): the speed
scale it asks for puts the protective separation of ISO/TS 15066 (the standard's formula,
`separation.protective_separation`, at the scaled speed and stopping time) exactly at
the obstacle's distance, with the robot's speed towards it measured by finite
differences of forward kinematics; and the motion's clock slows and recovers."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from planning_helpers import A_MAX, A, moving_executive, run_steps  # noqa: E402

from earcore.planning.executive import REACTION_TIME  # noqa: E402
from earcore.planning.reflex import ObstacleTrack  # noqa: E402
from earcore.planning.separation import protective_separation  # noqa: E402

PAN = np.array([A, A + [2.5, 0.0, 0.0, 0.0, 0.0, 0.0]])  # a long pan swing: a stretch at cruise speed


@pytest.fixture
def cruising(ur5):
    """An executive running the pan swing, its clock in the middle of the swing, and the
    tool's position, unit direction of travel and speed there (finite differences)."""
    executive = moving_executive(ur5, earcore.OcTree(0.05), A, np.zeros(6))
    assert executive.start_plan(PAN)
    trajectory = executive.motion.trajectory
    executive.motion.elapsed = t = trajectory.duration / 2
    h = 1e-4
    q0, q1 = trajectory.sample(np.array([t, t + h]))
    executive.cell.q, executive.command = q0, (q1 - q0) / h  # on the motion, at its speed
    p0, p1 = ur5.fk(np.stack([q0, q1]))[:, -1, :3, 3]
    velocity = (p1 - p0) / h
    stopping = float(np.max(np.abs((q1 - q0) / h) / A_MAX))
    return executive, q0, p0, velocity / np.linalg.norm(velocity), float(np.linalg.norm(velocity)), stopping


def _track(ur5, tool, direction, distance, velocity=(0.0, 0.0, 0.0)) -> ObstacleTrack:
    track = ObstacleTrack(0, [(0.0, tool + distance * direction)])
    track.clearance, track.on_robot, track.on_obstacle = distance, tool, tool + distance * direction
    track.link, track.own_velocity = len(ur5.link_names) - 1, np.asarray(velocity, dtype=np.float64)
    return track


def _separation(scale, speed, stopping, human_speed, config):
    return protective_separation(
        human_speed,
        scale * speed,
        reaction_time=REACTION_TIME,
        stopping_time=scale * stopping,
        sensor_uncertainty=config.ssm_uncertainty,
        robot_uncertainty=0.0,
    )


def test_the_scale_puts_the_protective_separation_at_the_obstacle(ur5, cruising):
    executive, q, tool, ahead, speed, stopping = cruising
    assert speed > 0.3  # the tool really moves
    config = executive.config
    for distance, human in ((0.15, 0.0), (0.3, 0.5), (0.6, 1.0)):
        executive.tracker.tracks = [_track(ur5, tool, ahead, distance, -human * ahead)]  # coming at `human` m/s
        scale = executive.ssm_scale(q)
        assert 0 < scale < 1
        assert _separation(scale, speed, stopping, human, config) == pytest.approx(distance, rel=1e-3)
    # A hand coming is kept further off than a still one; one leaving counts as still.
    executive.tracker.tracks = [_track(ur5, tool, ahead, 0.15)]
    still = executive.ssm_scale(q)
    executive.tracker.tracks = [_track(ur5, tool, ahead, 0.15, 0.5 * ahead)]
    assert executive.ssm_scale(q) == pytest.approx(still)
    executive.tracker.tracks = [_track(ur5, tool, ahead, 0.15, -0.5 * ahead)]
    assert executive.ssm_scale(q) < still
    # Behind the tool (it moves away) nothing slows; nearer than the uncertainty, it stops.
    executive.tracker.tracks = [_track(ur5, tool, -ahead, 0.1, 1.0 * ahead)]
    assert executive.ssm_scale(q) == 1.0
    executive.tracker.tracks = [_track(ur5, tool, ahead, 0.5 * config.ssm_uncertainty)]
    assert executive.ssm_scale(q) == 0.0
    # The slowest of several obstacles wins.
    executive.tracker.tracks = [_track(ur5, tool, ahead, 0.6), _track(ur5, tool, ahead, 0.15)]
    assert executive.ssm_scale(q) == pytest.approx(still)


def test_the_motion_slows_to_a_stop_on_its_path_and_recovers(ur5, cruising):
    executive, q, *_ = cruising
    trajectory = executive.motion.trajectory
    executive.ssm_target = 0.0
    states = run_steps(executive, 90)
    assert executive.speed_scale == 0.0
    # At rest, on the planned path (the clock, not the path, slowed).
    assert np.abs(executive.command).max() < 1e-6
    path = trajectory.sample(np.linspace(0, trajectory.duration, 4000))
    assert np.abs(states[:, None, :] - path[None]).max(axis=2).min(axis=1).max() < 0.01
    executive.ssm_target = 1.0
    run_steps(executive, 60)
    assert executive.speed_scale == 1.0
    # Rejoined the timing: running at the trajectory's own speed again.
    t = executive.motion.elapsed
    nominal = (trajectory.sample(t + 1e-3) - trajectory.sample(t)) / 1e-3
    assert executive.command == pytest.approx(nominal, abs=0.05)
