"""Time parameterisation within the speed and acceleration limits, braking, per-joint transfers, corner blends."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from planning_helpers import A_MAX, V_MAX, A, B  # noqa: E402

from earcore.planning import (  # noqa: E402
    JointSpacePlanner,
    time_parameterize,
)


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


@pytest.mark.parametrize("v_max, a_max", [([10.0, 0.3], 1000.0), ([1.0, 0.2], 20.0), ([1.57, 0.5], 8.0)])
def test_no_joint_exceeds_its_speed_on_the_segments_beside_a_corner(v_max, a_max):
    """A 30° corner between a stretch along joint 0 and one half along joint 1: the
    motion, differenced finely (the sampled positions themselves), keeps every joint
    within its limit on both segments. Capped by the corner's mean direction, joint 1
    ran at up to 2× its limit just after it."""
    path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0 + np.cos(np.pi / 6), np.sin(np.pi / 6)]])
    traj = time_parameterize(path, v_max, a_max)
    t = np.linspace(0.0, traj.duration, 200_001)
    speed = np.abs(np.diff(traj.sample(t), axis=0)) / np.diff(t)[:, None]
    assert (speed.max(axis=0) <= np.asarray(v_max) * (1 + 1e-6)).all(), speed.max(axis=0) / v_max
    assert (speed.max(axis=0) >= 0.95 * np.asarray(v_max)).any()  # and it is not merely slow


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
    for _ in range(5):
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
