"""What the planning tests share: the two poses A and B, the UR5's limits, a pillar
between them, a dense collision reference and a kinematic stand-in for the cell."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")


A = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0])
B = np.array([1.3, -1.3, 1.2, -1.5, -1.57, 0.0])
V_MAX = np.array([1.57, 1.57, 1.57, 1.57, 1.57, 1.57])
A_MAX = np.full(6, 1.8)
#: The pan joint swinging at 1.5 rad/s, and a plan that lifts the arm (joints 2-3):
#: the pan cannot stop at once, so the arm swings ~0.6 rad past the plan's start.
SWING = np.array([1.5, 0.0, 0.0, 0.0, 0.0, 0.0])
LIFT = np.array([A, A + [0.0, 0.5, -0.5, 0.0, 0.0, 0.0]])


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

    from earcore.planning.config import PlanningConfig
    from earcore.planning.executive import Executive, TripReport

    cell = KinematicCell(robot, q)
    executive = Executive(cell, SimpleNamespace(tree=tree, inserted_points=np.zeros((0, 3))), PlanningConfig(warmup=0.0, **planning), [B])
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
