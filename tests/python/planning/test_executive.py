"""The executive: the follower, the way the arm takes onto a plan, and its start and re-plan gates."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from planning_helpers import A_MAX, LIFT, SWING, V_MAX, A, dense_collides, moving_executive, run_steps, swing_voxel_tree  # noqa: E402


def test_follower_commands_stay_within_the_limits():
    from earcore.planning.follower import Follower

    rng = np.random.default_rng(3)
    follower = Follower(V_MAX, A_MAX)
    dt = 1 / 30
    for _ in range(200):
        q, now = rng.uniform(-3, 3, (2, 6))
        ahead = now + rng.uniform(-0.1, 0.1, 6)
        last = rng.uniform(-1.57, 1.57, 6)
        command = follower.command(q, last, now, ahead, dt)
        assert np.all(np.abs(command) <= V_MAX + 1e-12)
        assert np.all(np.abs(command - last) <= A_MAX * dt + 1e-12)
    # No reference: every joint brakes at its limit, and rests once it can.
    last = np.array([1.0, -0.5, 0.03, 0.0, -0.06, 0.2])
    assert follower.command(np.zeros(6), last, None, None, dt) == pytest.approx(
        np.sign(last) * np.maximum(np.abs(last) - A_MAX * dt, 0.0), abs=1e-15)
    # Bad input: clear errors from the core, never a panic.
    with pytest.raises(ValueError, match="limits"):
        Follower(V_MAX, np.zeros(6)).command(q, last, None, None, dt)
    with pytest.raises(ValueError, match="finite"):
        follower.command(q, last * np.nan, None, None, dt)
    with pytest.raises(ValueError, match="both"):
        follower.command(q, last, now, None, dt)
    with pytest.raises(ValueError, match="joints"):
        follower.command(q[:5], last, None, None, dt)
    with pytest.raises(ValueError, match="dt"):
        follower.command(q, last, None, None, 0.0)


@pytest.mark.parametrize("pan", [0.0, 2 * np.pi - 0.05])  # the second swings into the pan's limit
def test_rollout_is_the_motion_the_executive_runs(ur5, pan):
    start = A + [pan, 0, 0, 0, 0, 0]
    executive = moving_executive(ur5, earcore.OcTree(0.05), start, SWING)
    assert executive.start_plan(LIFT + [pan, 0, 0, 0, 0, 0])
    rollout = executive.follower.rollout(
        executive.motion.trajectory, start, SWING, executive.cell.config.time_step, ur5.joint_limits)
    assert rollout.rejoined and rollout.largest_error > 0.04  # a real detour, then back on the path
    # The executive's own loop on the cell's step rule passes through the same states.
    executed = run_steps(executive, len(rollout.states) - 1)
    np.testing.assert_allclose(np.vstack([start, executed]), rollout.states, atol=1e-12)
    # From there on the arm stays on the timed path.
    after = run_steps(executive, 30)
    t = executive.cell.time - executive.motion.start - 1 / 30 * np.arange(29, -1, -1)
    assert np.abs(after - executive.motion.trajectory.sample(t)).max() < 2e-3


def test_a_rejoined_arm_stays_on_its_motion():
    """Once the roll-out counts the arm back on its motion, the follower keeps it within
    a few mrad of it to the end: position and velocity both have to match (crossing
    the path at speed is not being on it)."""
    import dataclasses

    from earcore.planning.follower import Follower
    from earcore.planning.trajectory import time_parameterize

    rng = np.random.default_rng(11)
    limits = np.array([[-2 * np.pi, 2 * np.pi]] * 6)
    follower = Follower(V_MAX, A_MAX)
    onward = dataclasses.replace(follower, tolerance=-1.0, horizon=12.0)  # never rejoins: the whole run
    worst = 0.0
    for _ in range(40):
        path = np.cumsum(rng.uniform(-0.8, 0.8, (3, 6)), axis=0)
        trajectory = time_parameterize(path, V_MAX, A_MAX, control_period=1 / 30)
        command = rng.uniform(-1.5, 1.5, 6)
        rollout = follower.rollout(trajectory, path[0], command, 1 / 30, limits)
        if not rollout.rejoined:
            continue
        whole = onward.rollout(trajectory, path[0], command, 1 / 30, limits).states
        k = len(rollout.states) - 1
        np.testing.assert_array_equal(whole[: k + 1], rollout.states)
        t = np.arange(k, len(whole)) / 30
        worst = max(worst, float(np.abs(whole[k:] - trajectory.sample(t)).max()))
    assert 0 < worst < 3e-3


def test_a_plan_whose_way_on_is_blocked_does_not_start(ur5):
    executive = moving_executive(ur5, swing_voxel_tree(ur5)[0], A, SWING)
    assert not executive.start_plan(LIFT)
    assert executive.motion is None
    assert executive.log.refused_plans == [{"time": 0.0, "rejoined": True}]
    # The arm brakes instead, along its swing but without lifting: clear of the voxel.
    stopping = run_steps(executive, 30)
    assert not np.any(executive.command)
    assert not ur5.check_configurations(executive.tree, stopping).any()


def test_a_plan_the_arm_would_not_get_back_onto_in_time_does_not_start(ur5):
    from earcore.planning.follower import Follower

    executive = moving_executive(ur5, earcore.OcTree(0.05), A, SWING)
    executive.follower = Follower(V_MAX, A_MAX, horizon=0.5)  # the swing takes ~1.7 s
    assert not executive.start_plan(LIFT)
    assert executive.motion is None and executive.log.refused_plans[0]["rejoined"] is False


def test_a_cheaper_plan_is_costed_along_the_way_the_arm_takes(ur5):
    """A periodic switch to a cheaper plan compares the way the arm would take (its
    swing onto the plan included) with the current way, not the bare path."""
    executive = moving_executive(ur5, earcore.OcTree(0.05), A, SWING)
    way, _ = executive.way_onto(executive.timed(LIFT, plan=True))
    on_path, on_way = executive.planner.cost(LIFT), executive.planner.cost(way)
    assert on_way > 1.5 * on_path  # Eq. 4's length part: the swing is longer than the lift
    assert not executive.start_plan(LIFT, cheaper_than=0.5 * (on_path + on_way))
    assert executive.motion is None and not executive.log.refused_plans  # not refused for safety
    assert executive.start_plan(LIFT, cheaper_than=1.01 * on_way)


def test_a_reflex_timed_from_a_moving_arm_needs_a_clear_way_on(ur5):
    """Where the reflex's own motion (a stop, a transfer) is not clear, its path timed
    from here runs only if the follower's way onto it is clear too."""
    for tree, clear in ((earcore.OcTree(0.05), True), (swing_voxel_tree(ur5)[0], False)):
        executive = moving_executive(ur5, tree, A, SWING)
        executive.static_tree = tree.copy()
        assert not dense_collides(ur5, tree, LIFT)
        assert (executive.timed_reflex(LIFT, escape=False) is not None) == clear


def test_a_blocked_plan_stops_when_its_replacement_cannot_start(ur5):
    """on_frame: the running plan is blocked, the new plan's way on is blocked too: the
    arm stops (no motion; the follower brakes) rather than keep either."""
    from earcore.planning.executive import _Motion
    from earcore.planning.predictive import PlanChoice

    tree, widest = swing_voxel_tree(ur5)
    executive = moving_executive(ur5, tree, A, SWING, reflexes=False)
    # Running: a plan through the voxel (it appeared after the plan started).
    executive.motion = _Motion(executive.timed(np.array([A, widest]), plan=False), 0.0, "plan")
    executive._plan = lambda q: PlanChoice(LIFT, 0.0)
    executive.on_frame()
    assert executive.trip.stops == 1  # the running plan was blocked
    assert executive.motion is None
    assert len(executive.log.refused_plans) == 1


def test_a_recovery_started_on_a_blocked_frame_runs(ur5):
    """A blocked frame whose planning call finds the start touching the map starts a
    recovery (`_recover`): the blocked branch must not cancel it."""
    from earcore.planning.executive import _Motion

    tree, widest = swing_voxel_tree(ur5)
    executive = moving_executive(ur5, tree, A, SWING, reflexes=False)
    executive.motion = _Motion(executive.timed(np.array([A, widest]), plan=False), 0.0, "plan")
    recovery = executive.timed(np.array([A, A - [0.3, 0, 0, 0, 0, 0]]), plan=False)

    def plan_that_recovers(q):
        executive.motion = _Motion(recovery, executive.cell.time, "reflex")  # as `_recover` does
        return None

    executive._plan = plan_that_recovers
    executive.on_frame()
    assert executive.trip.stops == 1
    assert executive.motion is not None and executive.motion.trajectory is recovery


def test_a_running_plan_is_checked_along_the_way_the_arm_takes(ur5):
    tree = earcore.OcTree(0.05)
    executive = moving_executive(ur5, tree, A, SWING)
    assert executive.start_plan(LIFT)  # the map is empty: the swing is free
    run_steps(executive, 3)
    ahead = executive.remaining_way()
    # The way ahead: the roll-out from the arm's state now, then the knots after the
    # time it is back on the motion.
    trajectory, t = executive.motion.trajectory, executive.cell.time - executive.motion.start
    rollout = executive.follower.rollout(trajectory, executive.cell.q, executive.command, 1 / 30, ur5.joint_limits, start=t)
    assert rollout.rejoined and len(rollout.states) > 21
    np.testing.assert_array_equal(ahead, np.vstack([rollout.states, trajectory.positions[trajectory.times > t + rollout.duration]]))
    # Something appears where the rest of the swing goes, off the planned path.
    widest = ahead[np.abs(ahead[:, 0] - A[0]).argmax()]
    tree.update_nodes(ur5.fk(widest)[-1, :3, 3][None])
    assert executive.planner.rrt.path_is_valid(trajectory.remaining_path(t))
    assert not executive.planner.rrt.path_is_valid(ahead)
    # And the arm does go that way.
    np.testing.assert_allclose(run_steps(executive, 20), ahead[1:21], atol=1e-12)
