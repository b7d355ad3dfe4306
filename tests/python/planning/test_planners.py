"""RRT-Connect validated by the collision core, inverse kinematics, the danger-costed choice (Eq. 4)."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from planning_helpers import A, B, dense_collides, pillar_tree  # noqa: E402

from earcore.planning import (  # noqa: E402
    GoalInCollision,
    JointSpacePlanner,
    NoPathFound,
    PredictivePlanner,
    StartInCollision,
    UnreachablePose,
    solve_ik,
)


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


class _Path:
    """OMPL's path as the planner reads it: states that slice to joint values."""

    def __init__(self, waypoints):
        self.waypoints = [np.asarray(q, dtype=np.float64) for q in waypoints]

    def getStates(self):  # noqa: N802 (OMPL's name)
        return self.waypoints


def test_a_smoothed_path_that_collides_gives_way_to_a_less_simplified_one(ur5):
    """OMPL checks the edges it makes whole; splitting them (B-spline smoothing) samples
    them elsewhere, where a piece may collide. The planner returns the first of the
    smoothed, shortcut and raw solutions whose edges are all free at its resolution."""
    tree = pillar_tree()
    planner = JointSpacePlanner(ur5, tree, seed=7)
    planner.check_ends(A, B)
    (good,) = planner.plan(A, B, time_limit=1.0)
    assert planner.path_is_valid(good.waypoints)
    through = _Path([A, B])  # straight through the pillars
    assert not planner.path_is_valid(through.waypoints)
    chosen = planner._first_free([through, _Path(good.waypoints)])
    assert np.array_equal(chosen, good.waypoints)
    assert planner._first_free([through]) is None
    # Among cluttered pillars, every path returned passes the planner's own check.
    rng = np.random.default_rng(0)
    cells = [[x, y, z] for x, y in rng.uniform(-0.7, 0.7, (8, 2)) if np.hypot(x, y) >= 0.25
             for z in np.arange(0.025, 1.0, 0.05)]
    clutter = earcore.OcTree(0.05)
    clutter.update_nodes(np.array(cells))
    planner = JointSpacePlanner(ur5, clutter, seed=1)
    qs = ur5.random_configurations(200, seed=5)
    free = qs[~np.asarray(ur5.check_configurations(clutter, qs), dtype=bool)]
    for start, goal in zip(free[0:40:2], free[1:40:2]):
        try:
            (path,) = planner.plan(start, goal, time_limit=0.3)
        except NoPathFound:
            continue
        assert planner.path_is_valid(path.waypoints)


def test_ends_farther_apart_than_the_search_window_are_planned(ur5):
    """A joint that must turn farther than `max_joint_span`: the window around the ends'
    middle is widened to hold both (OMPL cannot start outside its space)."""
    tree = pillar_tree()
    span = float(np.max(np.abs(B - A))) * 0.5
    planner = JointSpacePlanner(ur5, tree, seed=7, max_joint_span=span)
    (solution,) = planner.plan(A, B, time_limit=2.0)
    assert np.allclose(solution.waypoints[0], A) and np.allclose(solution.waypoints[-1], B)
    assert not dense_collides(ur5, tree, solution.waypoints)


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


def test_ik_restarts_on_a_robot_with_a_continuous_joint(tmp_path):
    """A continuous joint has no limits to take the middle of (it was NaN, and every
    unseeded solve raised OverflowError): restarts sample it around 0."""
    path = tmp_path / "turn.urdf"
    path.write_text(
        """<robot name="turn">
  <link name="base"><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link>
  <link name="upper"><collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.03" length="0.4"/></geometry></collision></link>
  <link name="fore"><collision><origin xyz="0.15 0 0"/><geometry><box size="0.3 0.04 0.04"/></geometry></collision></link>
  <joint name="turn" type="continuous"><parent link="base"/><child link="upper"/><origin xyz="0 0 0.05"/><axis xyz="0 0 1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/><origin xyz="0 0 0.4"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2"/></joint>
</robot>"""
    )
    arm = earcore.robots.RobotModel.from_urdf(path)
    assert np.isinf(arm.joint_limits[0]).all()
    target = arm.fk([2.5, 0.7])[-1]
    result = solve_ik(arm, target)
    reached = arm.fk(result.q)[-1]
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) <= 0.01
    assert rotation_angle(reached[:3, :3] @ target[:3, :3].T) <= 0.1
    far = target.copy()
    far[:3, 3] += [2.0, 0.0, 0.0]
    with pytest.raises(UnreachablePose):
        solve_ik(arm, far, restarts=3)


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
    from reference import motion_danger_reference

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
