"""Planning (issue 7): time parameterisation, RRT-Connect with the collision core, the
danger-costed choice, obstacle tracking, risk and reflexes, the executive in the cell."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from earcore.planning import (  # noqa: E402
    GoalInCollision,
    JointSpacePlanner,
    NoPathFound,
    ObstacleTracker,
    PredictivePlanner,
    StartInCollision,
    UnreachablePose,
    plan_reflex,
    protective_separation,
    solve_ik,
    time_parameterize,
)

A = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0])
B = np.array([1.3, -1.3, 1.2, -1.5, -1.57, 0.0])
V_MAX = np.array([1.57, 1.57, 1.57, 1.57, 1.57, 1.57])
A_MAX = np.full(6, 1.8)


@pytest.fixture(scope="module")
def ur5():
    return earcore.robots.load("ur5")


def pillar_tree() -> earcore.OcTree:
    """A 10 × 10 cm pillar in the direct path of the tool from A to B."""
    tree = earcore.OcTree(0.05)
    pillar = np.array([[x, y, z] for x in (0.3, 0.35) for y in (0.35, 0.4) for z in np.arange(0.025, 0.9, 0.05)])
    tree.update_nodes(pillar)
    return tree


def dense_collides(robot, tree, path, step=0.005) -> bool:
    """Reference: every configuration of the polyline at `step` rad, checked one by one."""
    qs = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(np.abs(b - a).max() / step)))
        qs.extend(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return bool(robot.check_configurations(tree, np.array(qs)).any())


# --- time parameterisation ------------------------------------------------------------


@pytest.mark.parametrize("share", [0.5, 1.0])
@pytest.mark.parametrize("kind", ["polyline", "smooth"])
def test_trajectory_respects_limits_and_follows_the_path(kind, share):
    rng = np.random.default_rng(3)
    if kind == "polyline":
        path = A + np.cumsum(rng.normal(scale=0.4, size=(5, 6)), axis=0)
    else:
        s = np.linspace(0, 1, 150)[:, None]
        path = A + 0.6 * np.sin(3 * s + np.arange(6))
    dt = 1 / 30
    traj = time_parameterize(path, V_MAX, A_MAX, control_period=dt, straight_share=share)
    assert np.allclose(traj.sample(0.0), path[0]) and np.allclose(traj.sample(traj.duration), path[-1])
    # Every waypoint is passed (the knots include them).
    for w in path:
        assert np.abs(traj.positions - w).max(axis=1).min() < 1e-9
    # Speed limit at the knots; speed and acceleration by finite differences at the
    # controller's rate (the reference: what a controller sampling it would command).
    assert (np.abs(traj.velocities) <= V_MAX * (1 + 1e-9)).all()
    q = traj.sample(np.arange(0, traj.duration + dt, dt))
    v = np.diff(q, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    assert (np.abs(v) <= V_MAX * 1.001).all()
    assert (np.abs(a) <= A_MAX * 1.05).all()
    assert np.abs(v[0]).max() < 0.1 and np.abs(v[-1]).max() < 0.1  # rest to rest


@pytest.mark.parametrize("share", [0.5, 1.0])
@pytest.mark.parametrize("length", [1e-8, 1e-5, 1e-3, 0.3])
def test_short_moves_take_the_rest_to_rest_time(length, share):
    """A straight move from rest to rest under a tangential acceleration limit a takes
    2·sqrt(L / a) (accelerate half-way, brake half-way) while the speed limit is not
    reached. A move shorter than one resampling step once came out as 10^4-10^8 s (zero
    speed at both of its only two knots) and hung a reflex."""
    direction = np.array([1.0, -1.0, 0.5, 0.0, 0.0, 0.0]) / 1.5
    path = np.stack([A, A + length * direction])
    traj = time_parameterize(path, V_MAX, A_MAX, control_period=1 / 240, straight_share=share)
    # The tangential share of the acceleration is half of every joint's limit, or on a
    # straight line (no corner, no curvature) `straight_share` of it.
    moving = np.abs(direction) > 0
    a = np.min(share * A_MAX[moving] / np.abs(direction)[moving])
    assert traj.duration == pytest.approx(2 * np.sqrt(length / a), rel=0.05)
    assert np.allclose(traj.sample(traj.duration), path[-1])


def test_straight_stretches_may_use_the_whole_acceleration():
    """`straight_share=1` on random polylines and sampled curves: never slower than the
    split, faster on polylines with long straight stretches; on stretches more than
    CORNER_REACH segments from any corner the tangent accelerates or brakes at up to
    (and mostly at) a joint's whole limit unless the speed is at its cap, measured from
    the knot velocities, where the split uses half."""
    from earcore.planning.trajectory import CORNER_REACH

    rng = np.random.default_rng(11)
    for trial in range(10):
        if trial % 2:
            path = A + np.cumsum(rng.normal(scale=0.4, size=(4, 6)), axis=0)
        else:
            s = np.linspace(0, 1, 120)[:, None]
            path = A + rng.uniform(0.2, 0.8) * np.sin(rng.uniform(1, 4) * s + rng.uniform(0, 6, 6))
        split = time_parameterize(path, V_MAX, A_MAX)
        full = time_parameterize(path, V_MAX, A_MAX, straight_share=1.0)
        assert np.allclose(full.positions, split.positions)
        assert full.duration <= split.duration * (1 + 1e-12)
        if trial % 2 == 0:  # a sampled curve: corners every few segments
            continue
        assert full.duration < 0.9 * split.duration
        seg = np.diff(full.positions, axis=0)
        unit = seg / np.linalg.norm(seg, axis=1)[:, None]
        corner = np.flatnonzero(np.abs(np.diff(unit, axis=0)).max(axis=1) > 1e-6) + 1
        far = np.ones(len(seg), dtype=bool)
        for c in corner:
            far[max(0, c - CORNER_REACH) : c + CORNER_REACH] = False
        for traj, want in ((full, 1.0), (split, 0.5)):
            accel = np.diff(traj.velocities, axis=0) / np.diff(traj.times)[:, None]
            used = np.max(np.abs(accel) / A_MAX, axis=1)
            at_cap = np.max(np.abs(traj.velocities) / V_MAX, axis=1)
            capped = np.maximum(at_cap[:-1], at_cap[1:]) > 0.999
            moving = far & ~capped
            assert moving.sum() > 10
            assert np.all(used[moving] <= want * (1 + 1e-6))
            assert np.median(used[moving]) > 0.98 * want
            # Within CORNER_REACH segments of a corner the tangent keeps to half (the
            # corner's jump takes the rest); the curvature sits at the corner knots.
            near = ~far
            near[corner - 1] = near[corner] = False  # the segments touching a corner
            tangential = np.abs(accel[near]) / A_MAX
            assert near.sum() > 0 and np.all(tangential.max(axis=1) <= 0.5 * (1 + 1e-6))
    with pytest.raises(ValueError, match="straight_share"):
        time_parameterize(np.stack([A, B]), V_MAX, A_MAX, straight_share=1.5)


def test_trajectory_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        time_parameterize([[0.0, np.nan]], [1, 1], [1, 1])
    with pytest.raises(ValueError, match="> 0"):
        time_parameterize([[0.0, 0.0], [1.0, 1.0]], [1, 0], [1, 1])
    with pytest.raises(ValueError, match="shape"):
        time_parameterize(np.zeros(3), 1, 1)
    single = time_parameterize([[0.5, 0.5]], 1, 1)
    assert single.duration == 0.0 and np.allclose(single.sample(3.0), [0.5, 0.5])


def test_braking_stops_every_joint_at_its_limit_and_then_goes_on():
    """The stop from velocity v, differentiated numerically: v at the start, each joint
    decelerating at its own limit until it rests after |v_j| / a_j, at q_j + v_j·|v_j| /
    2a_j; `then` appends a move from rest there that keeps its own timing."""
    from earcore.planning.trajectory import braking

    q = np.array([0.1, -1.2, 1.0, -0.5, -1.57, 0.3])
    v = np.array([0.6, -0.3, 0.9, 0.0, 0.2, -0.1])
    a = np.array([1.8, 1.8, 1.2, 2.0, 2.0, 2.0])
    stop = braking(q, v, a)
    t_joint = np.abs(v) / a
    assert stop.duration == pytest.approx(t_joint.max())
    assert np.allclose(stop.end, q + v * np.abs(v) / (2 * a))
    dt = 1e-4
    t = np.arange(0.0, stop.duration + 0.1, dt)
    velocity = np.diff(stop.sample(t), axis=0) / dt
    assert np.allclose(velocity[0], v, atol=1e-3)
    accel = np.diff(velocity, axis=0) / dt
    for j in np.flatnonzero(v):
        braking_now = t[1:-1] < t_joint[j] - dt
        assert np.allclose(accel[braking_now, j], -np.sign(v[j]) * a[j], atol=1e-6)
        assert np.allclose(velocity[t[:-1] > t_joint[j] + dt, j], 0.0)
    move = time_parameterize(np.stack([stop.end, q]), V_MAX, A_MAX)
    both = stop.then(move)
    assert both.duration == pytest.approx(stop.duration + move.duration)
    for later in np.linspace(0, move.duration, 7):
        assert np.allclose(both.sample(stop.duration + later), move.sample(later))
    assert np.allclose(both.sample(np.array([0.0, both.duration])), [q, q])
    assert np.allclose(both.remaining_path(0.0)[0], q) and np.allclose(both.remaining_path(both.duration)[-1], q)
    still = braking(q, np.zeros(6), a)
    back = time_parameterize(np.stack([q, stop.end]), V_MAX, A_MAX)
    assert still.duration == 0.0 and np.allclose(still.then(back).sample(back.duration), stop.end)
    with pytest.raises(ValueError, match="start where"):
        stop.then(back)
    with pytest.raises(ValueError, match="finite"):
        braking(q, v + np.nan, a)


def test_transfer_is_each_joints_quickest_move_within_its_limits():
    """Every joint's profile from its current velocity to rest at the target, against
    a fine-stepped simulation of the time-optimal feedback law (speed command
    sign(e)·min(v_max, sqrt(2·a·|e|)), acceleration-limited): the same arrival times;
    and, differentiated numerically, the start velocity, the limits, rest at the end."""
    from earcore.planning.trajectory import transfer

    rng = np.random.default_rng(11)
    vmax, amax = np.array([0.8, 0.8, 0.8, 1.2, 1.2, 1.2]), np.array([1.8, 1.8, 1.5, 2.5, 2.5, 2.5])
    for trial in range(6):
        q = rng.uniform(-1, 1, 6)
        v = rng.uniform(-1, 1, 6) * vmax
        target = q + rng.uniform(-0.6, 0.6, 6)
        target[trial] = q[trial]  # one joint asked to stay: it brakes and comes back
        move = transfer(q, v, target, vmax, amax)
        assert np.allclose(move.sample(move.duration), target, atol=1e-12)
        dt = 1e-4
        t = np.arange(0.0, move.duration + 0.05, dt)
        x = move.sample(t)
        velocity = np.diff(x, axis=0) / dt
        assert np.allclose(velocity[0], v, atol=amax.max() * dt)
        assert np.all(np.abs(velocity) <= vmax + 1e-6)
        assert np.all(np.abs(np.diff(velocity, axis=0) / dt) <= amax + 1e-3)
        assert np.allclose(velocity[-10:], 0.0)
        # `path(step)` samples the curve with no joint moving more than step between samples.
        samples = move.path(0.02)
        assert np.abs(np.diff(samples, axis=0)).max() <= 0.02 + 1e-12
        assert np.allclose(samples[[0, -1]], [q, target])
        # Reference arrival per joint (step h): the feedback law reaches the target to
        # within 1e-4 rad at rest.
        h = 1e-4
        for j in range(6):
            xj, vj, time_ = q[j], v[j], 0.0
            while True:
                e = target[j] - xj
                if abs(e) < 1e-4 and abs(vj) < amax[j] * h * 2:
                    break
                want = np.sign(e) * min(vmax[j], np.sqrt(2 * amax[j] * abs(e)))
                vj = vj + np.clip(want - vj, -amax[j] * h, amax[j] * h)
                xj, time_ = xj + vj * h, time_ + h
            ours = move.joint_durations[j]
            assert ours == pytest.approx(time_, abs=0.01), (trial, j)
    with pytest.raises(ValueError, match="finite"):
        transfer(q, v, target + np.nan, vmax, amax)


def test_blend_corners_rounds_a_right_angle_with_the_analytic_arc():
    """(0,0)→(1,0)→(1,1) with deviation δ: tangent length δ·sin45°/(1−cos45°) = r, the
    arc on the circle of radius r about (1−r, r), its middle δ from the corner."""
    from earcore.planning.trajectory import blend_corners

    delta = 0.1
    out = blend_corners(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), delta, step=0.005)
    r = delta * np.sin(np.pi / 4) / (1 - np.cos(np.pi / 4))
    assert np.allclose(out[0], [0, 0]) and np.allclose(out[-1], [1, 1])
    assert np.allclose(out[1], [1 - r, 0])  # the arc leaves the first segment here
    arc = out[1:-1]
    assert np.allclose(np.linalg.norm(arc - [1 - r, r], axis=1), r)
    assert np.min(np.linalg.norm(arc - [1.0, 0.0], axis=1)) == pytest.approx(delta)
    assert np.linalg.norm(np.diff(arc, axis=0), axis=1).max() <= 0.005 + 1e-12
    assert np.allclose(arc[-1], [1, r])


def test_blend_corners_stays_near_the_polyline_and_is_faster_to_run():
    from earcore.planning.trajectory import blend_corners

    rng = np.random.default_rng(5)
    for trial in range(5):
        path = A + np.cumsum(rng.normal(scale=0.15, size=(12, 6)), axis=0)
        out = blend_corners(path, 0.1)
        assert np.allclose(out[0], path[0]) and np.allclose(out[-1], path[-1])
        # Brute force: every output point within the deviation of the polyline.
        t = np.linspace(0, 1, 400)[:, None]
        dense = np.vstack([a + (b - a) * t for a, b in zip(path[:-1], path[1:])])
        gap = np.linalg.norm(out[:, None, :] - dense[None], axis=2).min(axis=1)
        assert gap.max() <= 0.1 + 0.01
        # No corner left: consecutive chords turn by little (arcs sampled at 1 cm).
        chords = np.diff(out, axis=0)
        chords /= np.linalg.norm(chords, axis=1)[:, None]
        assert np.arccos(np.clip(np.einsum("ij,ij->i", chords[:-1], chords[1:]), -1, 1)).max() < 0.35
        # Durations of the planned motions (simulated seconds, deterministic), not timings.
        plain = time_parameterize(path, V_MAX, A_MAX).duration
        assert time_parameterize(out, V_MAX, A_MAX).duration < 0.9 * plain
    straight = np.stack([A, B])
    assert np.array_equal(blend_corners(straight, 0.1), straight)
    with pytest.raises(ValueError, match="finite"):
        blend_corners(np.array([A, A + np.nan, B]), 0.1)
    with pytest.raises(ValueError, match="max_deviation"):
        blend_corners(np.array([A, (A + B) / 2 + 0.1, B]), -0.1)


def test_plans_are_rounded_only_where_the_rounded_path_is_valid(ur5):
    from earcore.planning.trajectory import blend_corners

    planner = JointSpacePlanner(ur5, earcore.OcTree(0.05))
    path = np.array([A, (A + B) / 2 + 0.3, B])
    assert np.array_equal(planner.rounded(path, 0.1), blend_corners(path, 0.1))  # free space
    # The full deviation cuts into something, a quarter of it does not; then nothing fits.
    quarter = blend_corners(path, 0.025)
    planner.path_is_valid = lambda p: len(p) == len(quarter)
    assert np.array_equal(planner.rounded(path, 0.1), quarter)
    planner.path_is_valid = lambda p: False
    assert np.array_equal(planner.rounded(path, 0.1), path)
    assert np.array_equal(planner.rounded(path, 0.0), path)


@pytest.mark.parametrize("per_joint", [False, True])
def test_densify_matches_segment_by_segment_subdivision(per_joint):
    """Reference: each segment split on its own into the fewest equal parts no longer
    than the step (largest joint change, or Euclidean length), waypoints kept."""
    from earcore.planning.trajectory import densify

    rng = np.random.default_rng(11)
    for m in (1, 2, 3, 7):
        path = rng.normal(scale=0.3, size=(m, 6))
        if m > 2:
            path[2] = path[1]  # a zero-length segment
        expected = [path[0]]
        for a, b in zip(path[:-1], path[1:]):
            span = np.abs(b - a).max() if per_joint else np.linalg.norm(b - a)
            n = max(1, int(np.ceil(span / 0.05)))
            expected.extend(a + (b - a) * k / n for k in range(1, n + 1))
        out = densify(path, 0.05, per_joint=per_joint)
        assert out.shape == (len(expected), 6)
        assert np.allclose(out, np.array(expected), rtol=0, atol=1e-15)
        steps = np.diff(out, axis=0)
        size = np.abs(steps).max(axis=1) if per_joint else np.linalg.norm(steps, axis=1)
        assert (size <= 0.05 + 1e-12).all()
    with pytest.raises(ValueError, match="finite"):
        densify(np.array([[0.0] * 6, [np.nan] * 6]), 0.05, per_joint=per_joint)
    with pytest.raises(ValueError, match="step > 0"):
        densify(np.zeros((2, 6)), 0.0, per_joint=per_joint)


# --- RRT-Connect with the collision core ------------------------------------------------


def test_rrt_connect_paths_are_collision_free(ur5):
    tree = pillar_tree()
    assert ur5.check_motion(tree, A, B), "the scene must block the direct motion"
    planner = JointSpacePlanner(ur5, tree, seed=7)
    solutions = planner.plan(A, B, attempts=3, time_limit=1.0)
    assert len(solutions) >= 1
    for s in solutions:
        assert np.allclose(s.waypoints[0], A) and np.allclose(s.waypoints[-1], B)
        assert not dense_collides(ur5, tree, s.waypoints)
    assert planner.checks["states"] + planner.checks["motions"] > 0


def test_direct_motion_skips_the_search(ur5):
    planner = JointSpacePlanner(ur5, earcore.OcTree(0.05))
    (only,) = planner.plan(A, B)
    assert only.waypoints.shape == (2, 6) and planner.checks["states"] == 0


def test_planning_errors_name_the_cause(ur5):
    tree = pillar_tree()
    planner = JointSpacePlanner(ur5, tree, seed=1)
    tool_a = ur5.fk(A)[-1, :3, 3]
    blocked = earcore.OcTree(0.05)
    blocked.update_nodes(tool_a[None])
    with pytest.raises(StartInCollision, match="start"):
        JointSpacePlanner(ur5, blocked).plan(A, B)
    with pytest.raises(GoalInCollision, match="goal"):
        JointSpacePlanner(ur5, blocked).plan(B, A)
    with pytest.raises(NoPathFound):
        planner.plan(A, B, time_limit=1e-6, attempts=1)
    with pytest.raises(ValueError, match="joint values"):
        planner.plan(A[:5], B)
    with pytest.raises(ValueError, match="NaN"):
        planner.plan(np.full(6, np.nan), B)
    with pytest.raises(ValueError):
        planner.plan(A + np.r_[0, 0, 10, 0, 0, 0], B)  # outside the elbow's limits


# --- inverse kinematics for pose goals ---------------------------------------------------


def rotation_angle(r: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))


def test_ik_reaches_poses_of_random_configurations(ur5):
    rng = np.random.default_rng(4)
    for _ in range(8):
        target = ur5.fk(rng.uniform(-2, 2, 6))[-1]
        result = solve_ik(ur5, target, rng=rng)
        reached = ur5.fk(result.q)[-1]
        assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) <= 0.01
        assert rotation_angle(reached[:3, :3] @ target[:3, :3].T) <= 0.1


def test_ik_errors():
    ur5 = earcore.robots.load("ur5")
    far = np.eye(4)
    far[:3, 3] = [3.0, 0.0, 0.5]
    with pytest.raises(UnreachablePose, match="restarts"):
        solve_ik(ur5, far, restarts=3)
    skew = np.eye(4)
    skew[0, 1] = 0.5
    with pytest.raises(ValueError, match="rotation"):
        solve_ik(ur5, skew)


def test_planning_to_a_pose_goal(ur5):
    tree = pillar_tree()
    target = ur5.fk(B)[-1]
    (path, *_) = JointSpacePlanner(ur5, tree, seed=3).plan(A, target)
    reached = ur5.fk(path.waypoints[-1])[-1]
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) <= 0.01
    assert rotation_angle(reached[:3, :3] @ target[:3, :3].T) <= 0.1
    assert not dense_collides(ur5, tree, path.waypoints)


# --- danger-costed choice ------------------------------------------------------------------


def test_path_danger_is_the_sum_of_its_segments(ur5):
    tree = earcore.OcTree(0.05)
    blob = np.random.default_rng(0).uniform([0.1, 0.1, 0.3], [0.4, 0.5, 0.7], (300, 3))
    tree.insert_point_cloud(blob, [1.0, 1.0, 1.0])
    tree.end_frame(1 / 15)
    tree.insert_point_cloud(np.array([[2.0, 2.0, 2.0]]), [1.0, 1.0, 1.0])  # the blob is not hit again
    tree.end_frame(1 / 15)
    path = np.stack([A, (A + B) / 2 + 0.2, B])
    segments = ur5.motion_danger(tree, path[0], path[1], 0.05) + ur5.motion_danger(tree, path[1], path[2], 0.05)
    assert ur5.path_danger(tree, path, 0.05) == pytest.approx(segments, rel=1e-12)
    # Each segment is Eq. 4 as documented (the reference written in the tests).
    from conftest import motion_danger_reference

    reference = sum(motion_danger_reference(ur5, tree, path[i], path[i + 1], 0.05) for i in range(2))
    assert segments == pytest.approx(reference, rel=1e-9)
    assert segments > ur5.path_danger(earcore.OcTree(0.05), path, 0.05)  # danger adds cost


def test_predictive_planner_picks_the_cheapest_solution(ur5):
    tree = pillar_tree()
    # Danger on one side of the pillar (voxels hit once, then decaying).
    side = np.array([[x, y, z] for x in (0.15, 0.2, 0.25) for y in (0.2, 0.25) for z in np.arange(0.3, 0.8, 0.05)])
    tree.insert_point_cloud(side, [0.2, -0.8, 0.5])
    tree.end_frame(1 / 15)
    tree.insert_point_cloud(side + [0, 0, 2.0], [0.2, -0.8, 0.5])  # the side is seen free now
    tree.end_frame(1 / 15)
    planner = PredictivePlanner(ur5, tree, attempts=3, seed=11)
    choice = planner.plan(A, B)
    costs = [ur5.path_danger(tree, p.waypoints, 0.05) for p, _ in choice.candidates]
    assert choice.cost == pytest.approx(min(costs))
    assert np.array_equal(choice.path, choice.candidates[int(np.argmin(costs))][0].waypoints)
    assert choice.planning_time >= 0 and choice.optimisation_time > 0


# --- obstacles, risk and reflexes -------------------------------------------------------------


def test_cluster_points_match_a_flood_fill():
    rng = np.random.default_rng(5)
    res = 0.05
    cells = np.unique(rng.integers(0, 8, (120, 3)), axis=0)
    centres = (cells + 0.5) * res
    labels = earcore.cluster_points(centres, res)
    # Reference: flood fill over pairs whose cells differ by at most one per axis.
    near = (np.abs(cells[:, None] - cells[None]) <= 1).all(axis=2)
    comp = -np.ones(len(cells), int)
    for s in range(len(cells)):
        if comp[s] >= 0:
            continue
        comp[s] = s
        frontier = [s]
        while frontier:
            i = frontier.pop()
            for j in np.flatnonzero(near[i] & (comp < 0)):
                comp[j] = s
                frontier.append(j)
    assert ((labels[:, None] == labels[None]) == (comp[:, None] == comp[None])).all()
    with pytest.raises(ValueError):
        earcore.cluster_points(centres, 0.0)


def test_clearance_to_voxels_matches_sampled_capsules():
    from earcore.robots import urdf_path

    ur5c = earcore.RobotModel.from_urdf(urdf_path("ur5"), shape="capsule")
    rng = np.random.default_rng(2)
    res = 0.05
    for _ in range(5):
        q = A + rng.normal(scale=0.3, size=6)
        centres = (np.floor(rng.uniform([-0.6, -0.6, 0.0], [0.8, 0.8, 0.9], (40, 3)) / res) + 0.5) * res
        got = ur5c.clearance_to_voxels(centres, res, q)
        bodies = ur5c.bodies(q)
        best = np.inf
        moving = np.array(ur5c.fixed_to_root)[bodies["link"]] == False  # noqa: E712
        for a, b, r in zip(bodies["a"][moving], bodies["b"][moving], bodies["radius"][moving]):
            pts = a + (b - a) * np.linspace(0, 1, 2001)[:, None]
            outside = np.maximum(np.abs(pts[:, None, :] - centres[None]) - res / 2, 0.0)
            best = min(best, float(np.linalg.norm(outside, axis=2).min()) - r)
        if best > 0:
            assert got["distance"] <= best + 1e-9
            assert got["distance"] >= best - 1e-3  # axis sampled every ≤ 0.5 mm
            assert np.linalg.norm(got["on_robot"] - got["on_obstacle"]) == pytest.approx(got["distance"], abs=1e-9)
    assert ur5c.clearance_to_voxels(np.zeros((0, 3)), res, A)["distance"] == np.inf


def test_tracker_estimates_velocity_and_risk(ur5):
    res = 0.05
    tracker = ObstacleTracker(ur5, res, beta=1.5)
    table = np.array([[x, y, -0.025] for x in np.arange(-0.3, 1.0, res) for y in np.arange(-0.6, 0.6, res)])
    tracker.learn_static(table)
    blob = np.array([[x, y, z] for x in (0, res) for y in (0, res) for z in (0, res)])
    tool = ur5.fk(A)[-1, :3, 3]
    start = tool + np.array([0.6, 0.0, 0.0])
    velocity = np.array([-1.2, 0.0, 0.0])  # towards the tool
    report = None
    for k in range(6):
        t = k / 15
        centre = start + velocity * t
        voxels = (np.floor((blob + centre) / res) + 0.5) * res
        report = tracker.update(t, np.vstack([voxels, table]), A)
    assert len(tracker.tracks) == 1  # the table is static scene
    assert np.linalg.norm(tracker.tracks[0].velocity - velocity) < 0.25
    d = ur5.clearance_to_voxels(tracker.tracks[0].voxels, res, A)["distance"]
    assert report.clearance == pytest.approx(d)
    assert report.risk == pytest.approx(report.speed**2 / (1.5 * d))
    # The same obstacle moving away is no risk.
    away = ObstacleTracker(ur5, res)
    for k in range(6):
        voxels = (np.floor((blob + start - velocity * k / 15) / res) + 0.5) * res
        report = away.update(k / 15, voxels, A)
    assert report.risk == 0.0 and report.speed > 1.0


def test_tracker_rates_a_reaching_arm_by_its_hand(ur5):
    """An arm from a still shoulder whose hand comes at the tool at 1.2 m/s: its centroid
    moves at about half that, the hand's end of the cluster (the lead) at the hand's speed,
    and Eq. 2 takes the lead's."""
    res = 0.05
    tracker = ObstacleTracker(ur5, res, beta=1.5)
    tool = ur5.fk(A)[-1, :3, 3]
    shoulder = tool + np.array([1.1, 0.1, 0.0])
    hand0 = tool + np.array([0.7, 0.0, 0.0])
    velocity = np.array([-1.2, 0.0, 0.0])
    for k in range(6):
        hand = hand0 + velocity * k / 15
        line = shoulder + np.linspace(0, 1, 60)[:, None] * (hand - shoulder)
        voxels = np.unique((np.floor(line / res) + 0.5) * res, axis=0)
        report = tracker.update(k / 15, voxels, A)
    (track,) = tracker.tracks
    assert np.linalg.norm(track.velocity) < 0.8  # the centroid lags the hand
    assert np.linalg.norm(track.lead_velocity - velocity) < 0.25
    assert report.speed == pytest.approx(np.linalg.norm(track.lead_velocity))


def test_track_velocities_equal_least_squares_fits():
    """The tracker's two velocities (the slope over the window, and the
    constant-acceleration fit's velocity at the newest sample) against numpy's lstsq on
    the same samples: uneven frame times, two to six samples; degenerate times give
    the documented fallbacks (no velocity, or the slope)."""
    from earcore.planning.reflex import _velocities

    rng = np.random.default_rng(5)
    for n in range(2, 7):
        for _ in range(20):
            times = np.cumsum(rng.uniform(0.03, 0.1, n)) + rng.uniform(0, 100)
            positions = rng.normal(size=(n, 3))
            slope, now = _velocities([(float(t), p) for t, p in zip(times, positions)])
            design1 = np.stack([np.ones(n), times - times.mean()], axis=1)
            want_slope = np.linalg.lstsq(design1, positions, rcond=None)[0][1]
            np.testing.assert_allclose(slope, want_slope, rtol=1e-9, atol=1e-9)
            if n < 4:
                np.testing.assert_array_equal(now, slope)
                continue
            t = times - times[-1]
            design2 = np.stack([np.ones(n), t, t * t], axis=1)
            fit = np.linalg.lstsq(design2, positions, rcond=None)[0][1]
            want_now = fit if np.linalg.norm(fit) > np.linalg.norm(want_slope) else want_slope
            np.testing.assert_allclose(now, want_now, rtol=1e-7, atol=1e-7)
    p = rng.normal(size=(4, 3))
    assert not np.any(_velocities([(1.0, p[0])])[0])
    assert not np.any(_velocities([(1.0, x) for x in p])[1])  # one time: no velocity
    assert not np.any(_velocities([(0.1, x) for x in p[:3]])[0])  # (0.1's mean is not 0.1)
    two_times = [(1.0, p[0]), (1.0, p[1]), (2.0, p[2]), (2.0, p[3])]
    slope, now = _velocities(two_times)  # a line fits, a parabola does not: the slope
    np.testing.assert_allclose(slope, (p[2] + p[3] - p[0] - p[1]) / 2)
    np.testing.assert_array_equal(now, slope)


def test_tracker_follows_a_reach_that_speeds_up(ur5):
    """A hand accelerating at 6 m/s² towards the tool (seen as 5 cm voxels at 15 Hz):
    Eq. 2's speed is the hand's at the newest frame, where a plain slope over the
    window reports the speed of about a frame before (and fired a frame late)."""
    res = 0.05
    tracker = ObstacleTracker(ur5, res, beta=1.5)
    tool = ur5.fk(A)[-1, :3, 3]
    blob = np.array([[x, y, z] for x in (0, res) for y in (0, res) for z in (0, res)])
    start = tool + np.array([0.9, 0.0, 0.0])
    accel = 6.0
    for k in range(6):
        t = k / 15
        centre = start - np.array([0.5 * accel * t * t, 0.0, 0.0])
        report = tracker.update(t, (np.floor((blob + centre) / res) + 0.5) * res, A)
    (track,) = tracker.tracks
    true_speed = accel * 5 / 15  # 2.0 m/s at the newest frame
    assert report.speed == pytest.approx(true_speed, rel=0.15)
    lagging = float(np.linalg.norm(track.velocity))  # the slope over the last 4 frames
    assert lagging < 0.85 * true_speed
    # A constant 1.2 m/s, coarsely quantised (8 cm a frame in 5 cm voxels): never read
    # slower than the slope reads it, and over-read by at most about half (the price of
    # following accelerations; measured 1.53x at worst for this blob).
    steady = ObstacleTracker(ur5, res)
    for k in range(8):
        centre = start - np.array([1.2 * k / 15, 0.0, 0.0])
        report = steady.update(k / 15, (np.floor((blob + centre) / res) + 0.5) * res, A)
        track = steady.tracks[0]
        assert np.linalg.norm(track.velocity_now) >= np.linalg.norm(track.velocity) - 1e-12
        if k >= 3:
            assert np.linalg.norm(track.velocity_now) < 1.6 * 1.2


def test_a_lead_that_jumps_to_the_other_end_starts_again(ur5):
    """A still L-shaped bar, first seen whole, whose long arm's end the robot hides every
    other frame: the voxel farthest from where the track started switches ends (~0.4 m).
    That is another part, not a motion: the lead's history starts again instead of
    reading ~6 m/s. (Smaller flicker, under the jump, is what `still_speed` and the cap
    on the lead's speed are for.)"""
    res = 0.05
    tracker = ObstacleTracker(ur5, res)
    tool = ur5.fk(A)[-1, :3, 3]
    bar = (np.floor((tool + np.array([0.4, 0.0, 0.2]) + np.arange(10)[:, None] * [res, 0, 0]) / res) + 0.5) * res
    foot = bar[:2] - [0.0, 0.0, res]  # pulls the first centroid towards the left end
    for k in range(8):
        tracker.update(k / 15, np.vstack([foot, bar[:-3] if k % 2 else bar]), A)
        assert len(tracker.tracks[0].lead_history) == 1
        assert np.linalg.norm(tracker.tracks[0].lead_velocity) == 0.0


def test_keep_out_margin_around_tracked_obstacles(ur5):
    """A voxel 2.5 cm from the tool at A: not a collision, but within a 4 cm keep-out
    margin (the robot grown by 4 cm) for a state or a path passing A; left out when A
    is where a path or plan starts or ends (the reflexes deal with what is that close);
    off again with no voxels."""
    res = 0.05
    planner = JointSpacePlanner(ur5, earcore.OcTree(res))
    grown = earcore.robots.load("ur5", padding=0.005 + 0.04)
    grown.base = ur5.base
    probe = (np.floor(ur5.fk(A)[-1, :3, 3] / res) + 0.5) * res
    # Slide the voxel out along z until it is free of the robot, then 2.5 cm further.
    gap = None
    for dz in np.arange(0.0, 0.4, 0.005):
        tree = earcore.OcTree(res)
        tree.update_nodes((probe + [0, 0, dz])[None])
        d = ur5.clearance(tree, A)["distance"]
        if d >= 0.025:
            gap = probe + [0, 0, dz]
            break
    assert gap is not None
    voxel = (np.floor(gap / res) + 0.5) * res
    assert planner.is_valid(A)
    planner.set_keep_out(grown, voxel[None], res)
    d = ur5.clearance_to_voxels(voxel[None], res, A)["distance"]
    assert 0.02 <= d < 0.04 and not planner.is_valid(A)
    assert not planner.path_is_valid(np.stack([B, A, B]))
    assert planner.path_is_valid(np.stack([B, A]))
    path = planner.plan(A, B, time_limit=0.5)[0].waypoints
    assert np.allclose(path[0], A) and np.allclose(path[-1], B)
    planner.set_keep_out(grown, voxel[None], res)
    planner.set_keep_out(grown, np.zeros((0, 3)), res)
    assert planner.is_valid(A) and planner.path_is_valid(np.stack([B, A, B]))


def test_protective_separation_formula():
    # ISO/TS 15066: v_h (T_r + T_s) + v_r T_r + v_r T_s / 2 + C + Z_d + Z_r.
    got = protective_separation(1.6, 0.5, reaction_time=0.1, stopping_time=0.3, intrusion=0.02,
                                sensor_uncertainty=0.05, robot_uncertainty=0.01)
    assert got == pytest.approx(1.6 * 0.4 + 0.5 * 0.1 + 0.5 * 0.3 / 2 + 0.02 + 0.05 + 0.01)


def test_reflex_backtracks_or_moves_away(ur5):
    tree = earcore.OcTree(0.05)
    executed = A + np.linspace(0, 1, 50)[:, None] * (B - A)
    q = executed[-1]
    tool = ur5.fk(q)[-1, :3, 3]
    from earcore.planning.reflex import RiskReport

    obstacle = tool + np.array([0.12, 0.0, 0.0])
    report = RiskReport(0.0, 1, 2.0, 1.0, 0.1, tool, obstacle, 0.5, True, 0.0)
    move = plan_reflex(ur5, tree, q, executed, report, backtrack_fraction=0.1)
    assert move.kind == "backtrack"
    length = np.linalg.norm(B - A)
    back = np.linalg.norm(np.diff(move.path, axis=0), axis=1).sum()
    assert 0.1 * length <= back <= 0.1 * length + np.linalg.norm(executed[1] - executed[0]) + 1e-9
    # Block the way back: the reflex moves the tool away from the obstacle instead.
    # (the obstacle came from behind: the closest obstacle point is that voxel).
    behind = ur5.fk(executed[-8])[-1, :3, 3]
    tree.update_nodes(behind[None])
    assert not ur5.check_configurations(tree, q)
    obstacle = (np.floor(behind / 0.05) + 0.5) * 0.05
    report = RiskReport(0.0, 1, 2.0, 1.0, 0.05, tool, obstacle, 0.5, True, 0.0)
    move = plan_reflex(ur5, tree, q, executed, report, move_away_distance=0.1)
    assert move.kind == "move_away"
    new_tool = ur5.fk(move.path[-1])[-1, :3, 3]
    assert np.linalg.norm(new_tool - obstacle) > np.linalg.norm(tool - obstacle) + 0.05
    assert not ur5.check_motion(tree, move.path[0], move.path[-1])


def test_move_away_reuses_the_trackers_jacobian_only_at_its_configuration(ur5):
    """The tracker's report carries the closest point's Jacobian (for the closing
    speed); the move-away from the same configuration uses it and must come out as if
    it computed its own, and a report from another configuration must not lend it."""
    from dataclasses import replace

    from earcore.planning.reflex import _point_jacobian

    res = 0.05
    tracker = ObstacleTracker(ur5, res, beta=1.5)
    blob = np.array([[x, y, z] for x in (0, res) for y in (0, res) for z in (0, res)])
    tool = ur5.fk(A)[-1, :3, 3]
    qd = 0.3 * (B - A) / np.linalg.norm(B - A)
    for k in range(6):
        centre = tool + np.array([0.5, 0.0, 0.0]) + np.array([-1.2, 0.0, 0.0]) * k / 15
        report = tracker.update(k / 15, (np.floor((blob + centre) / res) + 0.5) * res, A, qd=qd)
    assert report.approaching and report.jacobian is not None
    assert np.array_equal(report.jacobian, _point_jacobian(ur5, A, report.link, report.on_robot))
    tree, dynamic = earcore.OcTree(res), tracker.last_dynamic
    kwargs = dict(prefer_move_away=True, dynamic=dynamic, voxel_size=res)
    move = plan_reflex(ur5, tree, A, np.array([A]), report, **kwargs)
    fresh = plan_reflex(ur5, tree, A, np.array([A]), replace(report, jacobian=None), **kwargs)
    assert move.kind == "move_away" and np.array_equal(move.path, fresh.path)
    # A poisoned Jacobian shows whether it is used: only at the report's own q.
    poisoned = replace(report, jacobian=np.zeros_like(report.jacobian))
    assert np.allclose(plan_reflex(ur5, tree, A, np.array([A]), poisoned, **kwargs).path[-1], A)
    elsewhere = A + 0.01
    own = plan_reflex(ur5, tree, elsewhere, np.array([elsewhere]), replace(report, jacobian=None), **kwargs)
    other = plan_reflex(ur5, tree, elsewhere, np.array([elsewhere]), poisoned, **kwargs)
    assert np.array_equal(own.path, other.path) and not np.allclose(other.path[-1], elsewhere)


def test_occupied_cells_near_splits_pruned_nodes():
    from earcore.planning.reflex import occupied_cells_near

    tree = earcore.OcTree(0.05)
    block = np.stack(np.meshgrid(*[np.arange(4) * 0.05 + 0.025] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    tree.update_nodes(block)  # a 20 cm cube of occupied cells
    tree.update_nodes(np.array([[0.525, 0.025, 0.025]]), occupied=False)
    tree.prune()
    assert len(tree.leaves()[0]) < 64  # pruned into bigger nodes
    for point, radius in (([0.0, 0.0, 0.0], 0.1), ([0.1, 0.1, 0.1], 0.06), ([0.3, 0.1, 0.1], 0.2)):
        point = np.array(point)
        cells = occupied_cells_near(tree, point, radius)
        expected = block[np.linalg.norm(block - point, axis=1) <= radius]
        assert sorted(map(tuple, np.round(cells, 6))) == sorted(map(tuple, np.round(expected, 6)))
    assert len(occupied_cells_near(tree, np.array([0.525, 0.025, 0.025]), 0.03)) == 0  # a free cell


def test_recovery_leaves_touched_voxels_and_runs_into_nothing_else(ur5):
    """A start in collision (a voxel inside the forearm, as a leaked or stale cell) gets
    a move along which the clearance to the cells around the contact never shrinks and
    ends positive; a move that would run into another part of the map, farther than the
    contact's neighbourhood, is refused."""
    from earcore.planning.reflex import plan_recovery
    from earcore.planning.trajectory import densify

    q = A + 0.5 * (B - A)
    frames = ur5.fk(q)
    inside = 0.5 * (frames[3, :3, 3] + frames[4, :3, 3])
    cell = (np.floor(inside / 0.05) + 0.5) * 0.05
    tree = earcore.OcTree(0.05)
    for _ in range(12):  # clamped: recovery must clear it in its check, not trip on it
        tree.update_nodes(inside[None])
    assert ur5.check_configurations(tree, q)
    move = plan_recovery(ur5, tree, q)
    assert move is not None and move.kind == "move_away"
    qs = densify(move.path, 0.02, per_joint=True)
    d = ur5.clearance_to_voxels(cell[None], 0.05, qs)["distance"]
    assert d[0] <= 0 < d[-1] and np.all(np.diff(d) >= -1e-3)
    # The same map plus a cell where that move takes the tool, far from the contact.
    tool_end = ur5.fk(move.path[-1])[-1, :3, 3]
    assert np.linalg.norm(tool_end - inside) > 0.3
    tree.update_nodes(tool_end[None])
    assert np.any(ur5.check_motions(tree, move.path[:-1], move.path[1:], 0.02))
    assert plan_recovery(ur5, tree, q) is None
    # Nothing touched: nothing to recover from.
    assert plan_recovery(ur5, earcore.OcTree(0.05), q) is None


def test_reflex_does_not_backtrack_into_an_obstacle_coming_from_behind(ur5):
    """The free way back is refused when it ends nearer the obstacle, where it is or where
    its velocity takes it in the horizon (checked against the exact distance); the reflex
    then moves away, and the move leaves the obstacle farther behind."""
    from earcore.planning.reflex import RiskReport

    res = 0.05
    tree = earcore.OcTree(res)
    executed = A + np.linspace(0, 1, 50)[:, None] * (B - A)
    q = executed[-1]
    tool = ur5.fk(q)[-1, :3, 3]
    behind = ur5.fk(executed[-12])[-1, :3, 3]
    # A small cluster 25 cm beyond the way back, coming at 1.2 m/s along it.
    heading = (behind - tool) / np.linalg.norm(behind - tool)
    centre = behind + 0.25 * heading
    voxels = (np.floor((centre + np.array([[x, y, 0.0] for x in (0, res) for y in (0, res)])) / res) + 0.5) * res
    c = ur5.clearance_to_voxels(voxels, res, q)
    velocity = -1.2 * heading
    report = RiskReport(0.0, 1, 3.0, 1.2, float(c["distance"]), c["on_robot"], c["on_obstacle"], 0.5, True, 0.0,
                        True, int(c["link"]), velocity, voxels)
    move = plan_reflex(ur5, tree, q, executed, report, dynamic=voxels, voxel_size=res, horizon=0.3)
    assert move is not None and move.kind == "move_away"
    end = ur5.clearance_to_voxels(voxels, res, move.path[-1])["distance"]
    assert end > c["distance"]
    # Without a velocity the obstacle sits still beyond the way back: backtracking still
    # heads towards it, so it is refused too; an obstacle ahead leaves the way back open.
    ahead = (np.floor((tool + 0.2 * (tool - behind) / np.linalg.norm(tool - behind)) / res) + 0.5) * res
    c = ur5.clearance_to_voxels(ahead[None], res, q)
    report = RiskReport(0.0, 1, 3.0, 1.2, float(c["distance"]), c["on_robot"], c["on_obstacle"], 0.5, True, 0.0,
                        True, int(c["link"]), np.zeros(3), ahead[None])
    move = plan_reflex(ur5, tree, q, executed, report, dynamic=ahead[None], voxel_size=res)
    assert move.kind == "backtrack"


def test_a_still_obstacle_is_no_reflex_matter(ur5):
    """A still cluster near the robot whose nearer half the robot hides every other frame:
    its centroid flickers by 2.5 cm, an estimated 0.075 m/s. Under `still_speed` it is not
    approaching and its risk is 0 while the robot moves towards it (once the track's
    velocity window is full); counted as moving (still_speed 0), the robot's own approach
    makes it a risk."""
    res = 0.05
    tool = ur5.fk(A)[-1, :3, 3]
    base = (np.floor((tool + np.array([0.15, 0.0, 0.0])) / res) + 0.5) * res
    full = base + np.array([[x, y, z] for x in (0, res) for y in (0, res) for z in (0, res)])
    far_half = full[full[:, 0] > base[0] + res / 2]
    qd = np.zeros(6)
    qd[1] = 0.4  # the shoulder lift brings the tool forward and down, towards the cluster
    worst = {}
    for still in (0.1, 0.0):
        tracker = ObstacleTracker(ur5, res, still_speed=still)
        risks = []
        for k in range(10):
            report = tracker.update(k / 15, full if k % 2 else far_half, A, qd=qd)
            if k >= tracker.window:  # once the velocity window is full
                risks.append(report.risk)
        worst[still] = max(risks)
        assert np.linalg.norm(tracker.tracks[0].velocity) < 0.1
    assert worst[0.1] == 0.0
    assert worst[0.0] > 0.0


# --- the executive in the cell -------------------------------------------------------------------


def test_reflex_layer_runs_single_threaded_and_restores_the_setting():
    from earcore.planning.executive import _on_this_thread

    before = earcore.get_num_threads()
    with pytest.raises(RuntimeError):
        with _on_this_thread():
            assert earcore.get_num_threads() == 1
            raise RuntimeError("a failing reflex step")
    assert earcore.get_num_threads() == before


class KinematicCell:
    """What the executive sees of the cell, without pybullet: the cell's own step rule
    (q ← clip(q + q̇·dt, limits), `SimulatedCell.step`) and the UR5's limits."""

    def __init__(self, robot, q, *, time_step=1 / 30):
        from types import SimpleNamespace

        self.model = robot
        self.config = SimpleNamespace(robot="ur5", padding=0.005, time_step=time_step)
        self.controller = SimpleNamespace(max_velocity=V_MAX, max_acceleration=A_MAX)
        self.person = None
        self.q = np.array(q, dtype=np.float64)
        self.time = 0.0
        self._commanded = np.zeros(robot.dof)

    def command_velocities(self, qd):
        self._commanded = np.asarray(qd, dtype=np.float64)

    def step(self):
        lo, hi = self.model.joint_limits.T
        self.q = np.clip(self.q + self._commanded * self.config.time_step, lo, hi)
        self.time += self.config.time_step

    def robot_person_distance(self):
        return float("inf")


def moving_executive(robot, tree, q, velocity, **planning):
    """An executive mid-trip whose arm is at q moving at `velocity` (rad/s), no motion
    running."""
    from types import SimpleNamespace

    from earcore.planning.executive import Executive, TripReport
    from earcore.sim.config import PlanningConfig

    cell = KinematicCell(robot, q)
    executive = Executive(cell, SimpleNamespace(tree=tree), PlanningConfig(warmup=0.0, **planning), [B])
    executive.trip = TripReport(goal=0, start_time=0.0)  # mid-trip: control() starts none
    executive.command = np.asarray(velocity, dtype=np.float64)
    return executive


def run_steps(executive, n):
    """n control steps of the executive on its cell; the states after each."""
    states = []
    for _ in range(n):
        executive.control(executive.cell.config.time_step)
        executive.cell.step()
        states.append(executive.cell.q.copy())
    return np.array(states)


#: The pan joint swinging at 1.5 rad/s, and a plan that lifts the arm (joints 2-3):
#: the pan cannot stop at once, so the arm swings ~0.6 rad past the plan's start.
SWING = np.array([1.5, 0.0, 0.0, 0.0, 0.0, 0.0])
LIFT = np.array([A, A + [0.0, 0.5, -0.5, 0.0, 0.0, 0.0]])


def swing_voxel_tree(robot) -> tuple[earcore.OcTree, np.ndarray]:
    """One voxel where the swing onto LIFT carries the tool, off LIFT's own path; and
    the swing's configuration there."""
    from earcore.planning.follower import Follower
    from earcore.planning.trajectory import time_parameterize

    trajectory = time_parameterize(LIFT, V_MAX, A_MAX, control_period=1 / 30)
    swing = Follower(V_MAX, A_MAX).rollout(trajectory, A, SWING, 1 / 30, robot.joint_limits).states
    widest = swing[np.abs(swing - A).max(axis=1).argmax()]
    tree = earcore.OcTree(0.05)
    tree.update_nodes(robot.fk(widest)[-1, :3, 3][None])
    # The reference: the plan's path is free, the states the arm would pass through are not.
    assert not dense_collides(robot, tree, LIFT)
    assert robot.check_configurations(tree, swing).any()
    return tree, widest


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
    assert executive._start_plan(LIFT + [pan, 0, 0, 0, 0, 0])
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
    assert not executive._start_plan(LIFT)
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
    assert not executive._start_plan(LIFT)
    assert executive.motion is None and executive.log.refused_plans[0]["rejoined"] is False


def test_a_cheaper_plan_is_costed_along_the_way_the_arm_takes(ur5):
    """A periodic switch to a cheaper plan compares the way the arm would take (its
    swing onto the plan included) with the current way, not the bare path."""
    executive = moving_executive(ur5, earcore.OcTree(0.05), A, SWING)
    way, _ = executive._way(executive._timed(LIFT, plan=True))
    on_path, on_way = executive.planner.cost(LIFT), executive.planner.cost(way)
    assert on_way > 1.5 * on_path  # Eq. 4's length part: the swing is longer than the lift
    assert not executive._start_plan(LIFT, cheaper_than=0.5 * (on_path + on_way))
    assert executive.motion is None and not executive.log.refused_plans  # not refused for safety
    assert executive._start_plan(LIFT, cheaper_than=1.01 * on_way)


def test_a_reflex_timed_from_a_moving_arm_needs_a_clear_way_on(ur5):
    """Where the reflex's own motion (a stop, a transfer) is not clear, its path timed
    from here runs only if the follower's way onto it is clear too."""
    from earcore.planning.reflex import copy_map

    for tree, clear in ((earcore.OcTree(0.05), True), (swing_voxel_tree(ur5)[0], False)):
        executive = moving_executive(ur5, tree, A, SWING)
        executive.static_tree = copy_map(tree)
        assert not dense_collides(ur5, tree, LIFT)
        assert (executive._timed_reflex(LIFT, escape=False) is not None) == clear


def test_a_blocked_plan_stops_when_its_replacement_cannot_start(ur5):
    """on_frame: the running plan is blocked, the new plan's way on is blocked too: the
    arm stops (no motion; the follower brakes) rather than keep either."""
    from earcore.planning.executive import _Motion
    from earcore.planning.predictive import PlanChoice

    tree, widest = swing_voxel_tree(ur5)
    executive = moving_executive(ur5, tree, A, SWING, reflexes=False)
    # Running: a plan through the voxel (it appeared after the plan started).
    executive.motion = _Motion(executive._timed(np.array([A, widest]), plan=False), 0.0, "plan")
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
    executive.motion = _Motion(executive._timed(np.array([A, widest]), plan=False), 0.0, "plan")
    recovery = executive._timed(np.array([A, A - [0.3, 0, 0, 0, 0, 0]]), plan=False)

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
    assert executive._start_plan(LIFT)  # the map is empty: the swing is free
    run_steps(executive, 3)
    ahead = executive._remaining()
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


@pytest.mark.slow
def test_executive_shuttles_in_the_cell(tmp_path):
    pytest.importorskip("pybullet")
    from earcore.run import run
    from earcore.sim.config import RunConfig

    config = RunConfig(duration=14.0, snapshots=[])
    config.cell.camera_scale = 0.25
    config.cell.person.enabled = False
    record = importlib.util.find_spec("rerun") is not None
    summary = run(config, tmp_path, progress=False, record=record, trips=2)
    trips = summary["trips"]
    assert len(trips) == 2 and all(t["completed"] for t in trips)
    assert summary["planning"]["collisions"] == 0
    # Without obstacles each trip is the direct motion at the limits: A to B and back.
    assert trips[0]["path_length"] == pytest.approx(np.linalg.norm(B - A), rel=0.02)
    if record:  # the recording shows the planned paths
        out = subprocess.run(
            [sys.executable, "-m", "rerun", "rrd", "print", "-v", str(tmp_path / "cell.rrd")],
            capture_output=True, text=True, timeout=120,
        ).stdout
        assert "world/plan/tool_path" in out


def test_fig7_circles_put_the_tool_on_its_circles():
    """The Fig. 7 driver's reference: during each circle the tool stays at the circle's
    radius and height while the pan joint turns once."""
    pytest.importorskip("pybullet")
    from earcore.perception import PerceptionPipeline
    from earcore.planning.experiments import CirclesDriver
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import RunConfig

    config = RunConfig()
    config.cell.person.enabled = False
    config.cell.camera_scale = 0.1
    cell = SimulatedCell(config.cell)
    pipeline = PerceptionPipeline(config.perception, cell.model)
    driver = CirclesDriver(cell, pipeline, repetitions=1)
    circles = [(start, data) for start, kind, data in driver.segments if kind == "circle"]
    assert len(circles) == 3
    for (start, (_, _, duration)), radius in zip(circles, driver.radii):
        qs = np.array([driver.reference(start + f * duration) for f in np.linspace(0, 1, 9)])
        tool = cell.model.fk(qs)[:, -1, :3, 3]
        assert np.allclose(np.linalg.norm(tool[:, :2], axis=1), radius, atol=0.006)
        assert np.allclose(tool[:, 2], driver.height + 0.1, atol=0.006)
        assert abs(qs[-1, 0] - qs[0, 0]) == pytest.approx(2 * np.pi)
    cell.close()


def test_fig7_measures_how_often_fading_voxels_are_seen_free():
    """The occlusion figure of Fig. 7's bands: of the frames in which a voxel was fading
    (hit before, not hit now), the share in which its danger went down (a ray saw it
    free). Fed a scripted danger map: an inner voxel that decays every other frame, an
    outer one that decays every frame, a voxel hit again (not fading) in between."""
    pytest.importorskip("pybullet")
    from types import SimpleNamespace

    from earcore.perception import PerceptionPipeline
    from earcore.planning.experiments import HIT_DANGER, CirclesDriver
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import RunConfig

    config = RunConfig()
    config.cell.person.enabled = False
    config.cell.camera_scale = 0.1
    cell = SimulatedCell(config.cell)
    driver = CirclesDriver(cell, PerceptionPipeline(config.perception, cell.model), repetitions=1)
    cell.close()
    inner = np.array([0.2 + 0.025, 0.025, driver.height + 0.025])
    outer = np.array([0.46 + 0.025, 0.025, driver.height + 0.025])
    middle = np.array([0.32 + 0.025, 0.025, driver.height + 0.025])
    c_inner = [HIT_DANGER, 0.9, 0.9, 0.8, 0.8, 0.7, HIT_DANGER, 0.95]
    c_outer = [HIT_DANGER, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3]
    c_middle = [0.5, 0.4, 0.3, 0.2, 0.1, 0.0, 0.0, 0.0]  # danger, but never hit: not the sweep
    for a, b, m in zip(c_inner, c_outer, c_middle):
        tree = SimpleNamespace(
            danger_voxels=lambda a=a, b=b, m=m: (np.array([inner, outer, middle]), None, np.array([a, b, m], np.float32))
        )
        driver.pipeline = SimpleNamespace(tree=tree)
        driver.on_frame()
    bands = {b["radius_m"]: b for b in driver.bands()}
    # Inner: fading in frames 1-5 and 7 (frame 6 is a hit), decayed in 1, 3, 5, 7.
    assert bands[0.2]["seen_free_while_fading"] == pytest.approx(4 / 6)
    assert bands[0.46]["seen_free_while_fading"] == pytest.approx(1.0)
    assert bands[0.2]["mean_danger"] == pytest.approx(np.mean(np.float32(c_inner)), rel=1e-6)
    # The sweep (hit in at least half of the one repetition): inner and outer, not middle.
    assert bands[0.2]["swept_voxels"] == 1 and bands[0.2]["mean_danger_swept"] == bands[0.2]["mean_danger"]
    assert bands[0.32]["voxels"] == 1 and bands[0.32]["swept_voxels"] == 0 and bands[0.32]["mean_danger_swept"] == 0.0
    assert bands[0.32]["mean_danger"] == pytest.approx(np.mean(np.float32(c_middle)), rel=1e-6)
