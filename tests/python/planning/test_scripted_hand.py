"""The executive against a scripted hand (no simulator): the hand's surface is inserted
into the map every map frame as a camera would see it, and the truth is the exact
clearance between the robot and the hand's cube.

- a hand passing 20 cm beside the moving tool, moving with it, fires no reflex and
  does not slow the arm (nothing approaches: separation monitoring has nothing to do;
  the prediction rule reads the hand's course from the tracker's steadier slopes);
- a hand heading for the tool's way at 1 m/s is met by a reflex or a stop in time,
  where without the reflex layer it touches the arm.

The scale separation monitoring asks for is tested against the standard's formula in
`test_separation_monitoring.py`.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import earcore

pytest.importorskip("ompl")

from planning_helpers import A, B, KinematicCell  # noqa: E402

DT = 1 / 30
CAMERA = np.array([1.5, 0.0, 1.2])
SIDE = 0.08


def cube_points(centre: np.ndarray, side: float = SIDE, step: float = 0.01) -> np.ndarray:
    g = np.arange(-side / 2, side / 2 + 1e-9, step)
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + centre


def run_with_hand(robot, hand_at, seconds: float, **planning):
    """Run an A-to-B trip on the kinematic cell for `seconds` with the hand's centre at
    `hand_at(t)` (None: no hand then). Returns the executive, the tool's positions per
    step and the smallest true robot-hand clearance."""
    from earcore.planning.config import PlanningConfig
    from earcore.planning.executive import Executive

    tree = earcore.OcTree(0.05)
    cell = KinematicCell(robot, A, time_step=DT)
    config = PlanningConfig(warmup=0.0, reflex_rule="prediction", **planning)
    executive = Executive(cell, SimpleNamespace(tree=tree, inserted_points=np.zeros((0, 3))), config, [A, B], seed=0)
    tools, closest, step = [], np.inf, 0
    while cell.time < seconds and not executive.trips:
        executive.control(DT)
        cell.step()
        executive.after_step()
        tools.append(robot.fk(cell.q)[-1, :3, 3])
        centre = hand_at(cell.time)
        if centre is not None:
            closest = min(closest, float(robot.clearance_to_voxels(centre[None], SIDE, cell.q)["distance"]))
        step += 1
        if step % 2 == 0:  # map frames at 15 Hz
            if centre is not None:
                tree.insert_point_cloud(cube_points(centre), CAMERA)
            tree.end_frame(2 * DT)
            executive.on_frame()
    return executive, np.array(tools), closest


@pytest.fixture(scope="module")
def free_trip(ur5):
    """The trip without a hand: the tool's positions per step and its duration."""
    executive, tools, _ = run_with_hand(ur5, lambda t: None, 8.0)
    assert executive.trips, "the free trip ends"
    return tools, executive.trips[0].execution_time


def test_a_hand_moving_beside_the_tool_neither_fires_nor_slows(ur5, free_trip):
    tools, duration = free_trip

    def beside(t):
        # radially outwards of the tool (the arm lies inwards), moving with it: the
        # cube's centre 30 cm from the tool's, the hand 20 cm from the robot
        tool = tools[min(int(round(t / DT)), len(tools) - 1)]
        out = np.array([tool[0], tool[1], 0.0])
        return tool + 0.30 * out / np.linalg.norm(out)

    executive, _, closest = run_with_hand(ur5, beside, 8.0)
    assert 0.18 < closest < 0.22
    assert executive.trips and executive.trips[0].reflexes == 0
    assert executive.trips[0].execution_time == pytest.approx(duration, abs=2 * DT)


def test_a_hand_heading_for_the_tool_is_met_in_time(ur5, free_trip):
    tools, duration = free_trip
    # From 0.55 m out, at 1 m/s, to where the tool will be 0.8 s later (arriving 0.25 s
    # before the tool would), then held there.
    start_time = 0.35 * duration
    k = int(round((start_time + 0.8) / DT))
    target = tools[k]
    out = np.array([target[0], target[1], 0.0])
    origin = target + 0.55 * out / np.linalg.norm(out)

    def heading(t):
        if t < start_time:
            return origin
        return origin + (target - origin) * min(1.0, (t - start_time) / 0.55)

    executive, _, closest = run_with_hand(ur5, heading, duration + 3.0)
    assert closest > 0.0, "no contact"
    assert executive.log.reflexes or executive.log.protective_stops
    # The reference: without the reflex layer (and the separation monitoring it runs)
    # the same hand touches the arm.
    _, _, unguarded = run_with_hand(ur5, heading, duration + 3.0, reflexes=False)
    assert unguarded < 0.0
