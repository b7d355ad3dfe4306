"""Degenerate robots and sizes from user data: refused with a clear error at
construction, or working in every call, never a panic or an allocation abort; and the
collision checks and the clearance agree on what they refuse."""

from __future__ import annotations

import numpy as np
import pytest

import earcore
import earcore.robots as robots

REVOLUTE = ("shoulder", "revolute", 0, 1, (0.0, 0.0, 0.2), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), -3.0, 3.0)


def arm(bodies, joints=(REVOLUTE,), links=("base", "arm")):
    return earcore.RobotModel(list(links), list(joints), list(bodies))


def one_voxel(centre, resolution=0.05):
    tree = earcore.OcTree(resolution)
    tree.update_nodes(np.array([centre], dtype=float))
    return tree


def box_distance(p, lo, hi):
    return float(np.linalg.norm(p - np.clip(p, lo, hi)))


# --- refused at construction --------------------------------------------------------------


@pytest.mark.parametrize(
    "links, joints",
    [
        (["only"], []),
        (["base", "plate"], [("weld", "fixed", 0, 1, (0, 0, 0.1), (0, 0, 0), (0, 0, 1), 0.0, 0.0)]),
    ],
)
def test_a_robot_without_movable_joints_is_refused(links, joints):
    # Its configurations would be empty: every batched call once panicked on them.
    with pytest.raises(ValueError, match="no movable joints"):
        earcore.RobotModel(links, joints, [None] * len(links))


def test_a_urdf_without_movable_joints_is_refused(tmp_path):
    path = tmp_path / "welded.urdf"
    path.write_text(
        """<robot name="welded">
  <link name="base"/><link name="plate"/>
  <joint name="weld" type="fixed"><parent link="base"/><child link="plate"/></joint>
</robot>"""
    )
    with pytest.raises(ValueError, match="no movable joints"):
        robots.RobotModel.from_urdf(path)


@pytest.mark.parametrize(
    "body, joint, message",
    [
        (((0, 0, 0), (0, 0, 1e5), 0.05, "capsule"), REVOLUTE, "within 10000 m"),
        (((0, 0, 0), (0, 0, 0.5), 1e300, "cylinder"), REVOLUTE, "within 10000 m"),
        (((0, 0, 0), (0, 0, 0.5), np.nan, "capsule"), REVOLUTE, "radius"),
        (((0, 0, 0), (0, 0, 0.5), -0.1, "capsule"), REVOLUTE, "radius >= 0"),
        (((0, 0, 0), (0, 0, 0.5), 0.05, "capsule"), REVOLUTE[:4] + ((2e4, 0, 0),) + REVOLUTE[5:], "origin xyz"),
        (((0, 0, 0), (0, 0, 0.5), 0.05, "capsule"), ("slide", "prismatic", 0, 1, (0, 0, 0), (0, 0, 0), (1, 0, 0),
                                                     -1e6, 1.0), "beyond 10000 m"),
    ],
)
def test_absurd_geometry_is_refused_with_the_link_or_joint_named(body, joint, message):
    # Lengths this large only come from unit mistakes or garbage; they made the reach
    # infinite and the collision index's cell arithmetic wrap.
    with pytest.raises(ValueError, match=message):
        arm([None, body], joints=[joint])


# --- degenerate but valid robots work in every call -----------------------------------------


def every_call(robot, tree, q):
    """Each query of the model at one configuration, by name."""
    qs = np.array([q, q])
    return {
        "fk": robot.fk(q),
        "fk batch": robot.fk(qs),
        "jacobian": robot.jacobian(q, robot.dof, [0.1, 0.0, 0.3]) if robot.dof < len(robot.link_names) else None,
        "frame_jacobian": robot.frame_jacobian(q, len(robot.link_names) - 1),
        "bodies": robot.bodies(q),
        "self_filter": robot.self_filter(np.zeros((4, 3)), q),
        "check_configurations": robot.check_configurations(tree, qs),
        "check_motion": robot.check_motion(tree, q, q),
        "check_motions": robot.check_motions(tree, qs, qs),
        "self_collisions": robot.self_collisions(qs),
        "clearance": robot.clearance(tree, qs),
        "clearance_to_voxels": robot.clearance_to_voxels(np.zeros((1, 3)), 0.05, qs),
        "touches_voxels": robot.touches_voxels(np.zeros((1, 3)), 0.05, qs),
        "motion_danger": robot.motion_danger(tree, q, q),
        "path_danger": robot.path_danger(tree, qs),
    }


def test_a_robot_without_bodies_answers_every_call():
    robot = arm([None, None])
    tree = one_voxel([0.0, 0.0, 0.2])
    out = every_call(robot, tree, [0.3])
    # Nothing to collide, filter or measure; the kinematics still move the frame.
    assert out["bodies"]["radius"].shape == (0,) and out["bodies"]["a"].shape == (0, 3)
    assert out["self_filter"].all()
    assert not out["check_configurations"].any() and not out["check_motion"] and not out["check_motions"].any()
    assert not out["self_collisions"].any() and not out["touches_voxels"].any()
    assert np.isinf(out["clearance"]["distance"]).all() and (out["clearance"]["link"] == -1).all()
    assert np.isinf(out["clearance_to_voxels"]["distance"]).all()
    assert out["motion_danger"] == 0.0 and out["path_danger"] == 0.0
    assert np.allclose(out["fk"][1][:3, :3], [[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])


@pytest.mark.parametrize("shape", ["capsule", "cylinder"])
def test_a_zero_length_body_is_a_ball_or_a_disc_in_every_call(shape):
    # A zero-length capsule is a ball; a zero-length cylinder is a flat disc inside that
    # ball. Either sits 0.3 m out on the arm, swept past one voxel.
    robot = arm([None, ((0.3, 0.0, 0.0), (0.3, 0.0, 0.0), 0.04, shape)])
    voxel = np.array([0.0, 0.325, 0.225])  # the cell [0, 0.05) × [0.3, 0.35) × [0.2, 0.25)
    tree = one_voxel(voxel)
    lo, hi = np.array([0.0, 0.3, 0.2]), np.array([0.05, 0.35, 0.25])
    angles = np.linspace(-3.0, 3.0, 121)
    centres = np.array([[0.3 * np.cos(a), 0.3 * np.sin(a), 0.2] for a in angles])
    gaps = np.array([box_distance(c, lo, hi) for c in centres])
    out = every_call(robot, tree, [angles[0]])
    assert out["bodies"]["radius"].tolist() == [pytest.approx(0.04)]
    assert np.allclose(out["bodies"]["a"], out["bodies"]["b"])
    hits = robot.check_configurations(tree, angles[:, None])
    decided = np.abs(gaps - 0.04) > 1e-6
    if shape == "capsule":
        # A ball: colliding exactly where the centre is within r of the voxel box, and
        # its clearance is the gap less r.
        assert np.array_equal(hits[decided], (gaps <= 0.04)[decided])
        clearance = robot.clearance(tree, angles[:, None])["distance"]
        # The index's bound: never below the truth, at most res·(1/4 + 1.5·√3) above.
        assert np.all(clearance >= gaps - 0.04 - 1e-9)
        assert np.all(clearance <= gaps - 0.04 + 0.05 * (0.25 + 1.5 * np.sqrt(3)))
    else:
        # A disc lies inside the ball: never a hit where the ball misses.
        assert not hits[gaps > 0.04 + 1e-6].any()
    assert hits.any() and not hits.all()


def test_a_zero_radius_body_and_fixed_links_after_the_joint():
    # One movable joint, then two fixed links, the last with a zero-radius segment.
    joints = [
        REVOLUTE,
        ("weld", "fixed", 1, 2, (0.2, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.0, 0.0),
        ("tip", "fixed", 2, 3, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.0, 0.0),
    ]
    robot = arm([None, None, None, ((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.0, "capsule")], joints=joints,
                links=("base", "arm", "wrist", "tool"))
    # The segment from (0.3, 0, 0.2) to (0.4, 0, 0.2) at q = 0.
    tree = one_voxel([0.375, 0.025, 0.225])
    out = every_call(robot, tree, [0.0])
    assert bool(out["check_configurations"][0])  # the segment runs along the voxel's edge
    assert out["clearance"]["distance"][0] <= 0.0
    assert not robot.check_configurations(tree, [1.0])
    assert robot.clearance(tree, [1.0])["distance"] > 0.1


# --- sizes from user data -------------------------------------------------------------------


def test_motion_danger_refuses_more_samples_than_it_bounds():
    # A 20 m link on a 1 cm map is 2000 samples per configuration; at 1e-5 rad steps a
    # 2 rad motion is 2e5 configurations: 4e8 point steps, past the bound. Once it
    # allocated whatever the body's length asked for (capacity overflow or abort).
    robot = arm([None, ((0.0, 0.0, 0.0), (20.0, 0.0, 0.0), 0.05, "capsule")])
    tree = earcore.OcTree(0.01)
    with pytest.raises(ValueError, match="motion_danger would sample"):
        robot.motion_danger(tree, [-1.0], [1.0], resolution=1e-5)
    with pytest.raises(ValueError, match="motion_danger would sample"):
        robot.path_danger(tree, [[-1.0], [1.0]], resolution=1e-5)
    # The same call at a sane resolution: the tip sweeps 2 rad at up to 20 m, the mean
    # over the body's points is the path of its middle (2 rad × 10 m) with no danger.
    assert robot.motion_danger(tree, [-1.0], [1.0], resolution=0.01) == pytest.approx(20.0, rel=1e-3)


def test_check_motion_refuses_more_steps_than_memory_holds():
    robot = arm([None, ((0.0, 0.0, 0.0), (0.3, 0.0, 0.0), 0.05, "capsule")])
    tree = one_voxel([1.0, 1.0, 1.0])
    for call in (
        lambda: robot.check_motion(tree, [-3.0], [3.0], resolution=1e-12),
        lambda: robot.check_motions(tree, [[-3.0]], [[3.0]], resolution=5e-324),
        lambda: robot.motion_danger(tree, [-3.0], [3.0], resolution=1e-12),
    ):
        with pytest.raises(ValueError, match="resolution"):
            call()


# --- the checks and the clearance refuse the same things --------------------------------------


def far_base(x):
    base = np.eye(4)
    base[0, 3] = x
    return base


@pytest.mark.parametrize(
    "case",
    ["outside the limits", "NaN", "wrong length", "base beyond the map", "base far beyond the map",
     "index too large"],
)
def test_clearance_and_the_collision_checks_refuse_alike(case):
    ur5 = robots.load("ur5")
    tree = one_voxel([0.3, 0.3, 0.3])
    q = np.zeros(6)
    if case == "outside the limits":
        q[0] = 7.0
    elif case == "NaN":
        q[2] = np.nan
    elif case == "wrong length":
        q = np.zeros(5)
    elif case == "base beyond the map":
        ur5.base = far_base(1637.5)  # the 5 cm map ends at ±1638.4 m; the 1.38 m reach does not fit
    elif case == "base far beyond the map":
        # Grid coordinates of this base overflow 64-bit integers: once the index's region
        # wrapped (printed inverted), checks raised and the clearance said "inf".
        ur5.base = far_base(1e20)
    elif case == "index too large":
        tree = one_voxel([0.3, 0.3, 0.3], resolution=2e-4)
    errors = []
    for call in (
        lambda: ur5.check_configurations(tree, q),
        lambda: ur5.clearance(tree, q),
        lambda: ur5.check_motion(tree, q, q),
        lambda: ur5.check_motions(tree, q[None], q[None]),
    ):
        with pytest.raises((ValueError, earcore.EarcoreError)) as info:
            call()
        errors.append((type(info.value), str(info.value)))
    # The same parameter name in the two batched queries: the same error, word for word;
    # the motion checks name their own parameters, so only the kind must match.
    assert errors[0] == errors[1], errors
    assert len({kind for kind, _ in errors}) == 1, errors
    if case.startswith("base"):
        assert errors[0][0] is earcore.OutOfMapError and "robot's base" in errors[0][1]
    if case == "index too large":
        assert "collision index" in errors[0][1] and "cells" in errors[0][1]


def test_an_empty_map_and_a_robot_beyond_it_is_an_error_not_inf():
    ur5 = robots.load("ur5")
    ur5.base = far_base(5000.0)
    empty = earcore.OcTree(0.05)
    for call in (lambda: ur5.clearance(empty, np.zeros(6)), lambda: ur5.check_configurations(empty, np.zeros(6))):
        with pytest.raises(earcore.OutOfMapError, match="robot's base"):
            call()
    # Back inside, both answer: nothing there.
    ur5.base = far_base(1000.0)
    assert ur5.clearance(empty, np.zeros(6))["distance"] == np.inf
    assert not ur5.check_configurations(empty, np.zeros(6))
