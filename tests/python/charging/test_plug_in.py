"""The three-step plug-in against pybullet's contacts: the true port pose goes in, a
pose turned well past what the pins' clearance and round tips forgive is blocked and
stopped by the force, a port out of reach or of the wrong type is refused before the
robot moves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from earcore import robots
from earcore.charging.plug_in import PlugInConfig, PortOutOfReach, plan_plug_in, plug_in, unplug
from earcore.charging.session import charge
from earcore.errors import ConfigError
from earcore.sim.charging_cell import STANDBY, ChargingCell, ChargingCellConfig
from earcore.sim.compliant_holder import Compliance
from earcore.transforms import axis_angle_matrix

pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def ur10():
    model = robots.load("ur10")
    return model, model.link_names.index(robots.FLANGES["ur10"][0])


def _port_frame(cell) -> np.ndarray:
    """The plug's true tip frame in the port's frame."""
    return np.linalg.inv(cell.base_from_port) @ cell.base_from_plug()


def _run(cell, ur10, base_from_port):
    model, link = ur10
    plan = plan_plug_in(model, link, cell.flange_from_tip, base_from_port, cell.joints, cell.plug_connector.insertion_depth)
    result = plug_in(cell, plan)
    return result, _port_frame(cell)


def test_the_true_pose_plugs_in_and_out(ur10):
    cell = ChargingCell(ChargingCellConfig(seed=4, camera_scale=0.25))
    try:
        config = PlugInConfig()
        result, at = _run(cell, ur10, cell.base_from_port)
        assert result.inserted and result.stopped_by_force
        # the plug sits mated: its tip on the port's face (within 1 mm), on the axis
        assert abs(at[2, 3]) < 0.001 and np.linalg.norm(at[:2, 3]) < cell.plug_connector.clearance
        assert config.force_threshold <= result.peak_force < config.force_limit
        unplug(cell, result, STANDBY, config)
        assert np.allclose(cell.joints, STANDBY)
        # out and back in its holder: well clear of the port
        assert _port_frame(cell)[2, 3] > 0.2
    finally:
        cell.close()


def test_a_turned_pose_is_blocked_by_the_pins_and_stopped_by_the_force(ur10):
    cell = ChargingCell(ChargingCellConfig(seed=5, camera_scale=0.25))
    try:
        wrong = cell.base_from_port
        wrong[:3, :3] = wrong[:3, :3] @ axis_angle_matrix([0.0, 0.0, 1.0], np.radians(8.0))
        result, at = _run(cell, ur10, wrong)
        assert result.stopped_by_force and not result.inserted
        # the pins' tips rest on the face: the plug is a pin's length out
        assert at[2, 3] == pytest.approx(cell.plug_connector.pin_length, abs=0.001)
        assert result.peak_force < PlugInConfig().force_limit
    finally:
        cell.close()


def _moved_along_axis(pose: np.ndarray, offset: float, turn_deg: float = 0.0) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += pose[:3, 2] * offset
    out[:3, :3] = out[:3, :3] @ axis_angle_matrix([0.0, 0.0, 1.0], np.radians(turn_deg))
    return out


def test_a_pin_met_while_aligning_stops_there(ur10):
    """A port believed 10 mm deeper (and turned): the pins meet the face during the
    align step, which stops at the threshold; the insert step is not tried."""
    cell = ChargingCell(ChargingCellConfig(seed=4, camera_scale=0.25))
    try:
        result, at = _run(cell, ur10, _moved_along_axis(cell.base_from_port, -0.010, 8.0))
        assert result.stopped_by_force and not result.inserted
        assert result.depth == pytest.approx(-PlugInConfig().standoff)
        assert result.peak_force < PlugInConfig().force_limit
        assert at[2, 3] == pytest.approx(cell.plug_connector.pin_length, abs=0.001)  # resting on the face
        unplug(cell, result, STANDBY, PlugInConfig(pause=0.0))  # backs out without a spike
    finally:
        cell.close()


def test_a_port_shallower_than_believed_is_not_reached(ur10):
    """A port believed 8 mm in front of where it is: the commanded travel ends before
    the plug meets it. Not stopped by force, not inserted."""
    cell = ChargingCell(ChargingCellConfig(seed=6, camera_scale=0.25))
    try:
        result, at = _run(cell, ur10, _moved_along_axis(cell.base_from_port, 0.008))
        assert not result.stopped_by_force and not result.inserted
        assert at[2, 3] > 0.001  # short of mated
    finally:
        cell.close()


def test_a_steep_parking_is_planned_with_the_arm_clear_of_the_car(ur10):
    """A port at 45° to the cameras: the arm configuration nearest stand-by would sweep
    the upper arm through the car's side; another is found, and every joint of every
    waypoint stays in front of the car's side (the port's plane, by forward kinematics)."""
    model, link = ur10
    cell = ChargingCell(ChargingCellConfig(seed=0, camera_scale=0.25))
    try:
        for _ in range(10):
            cell.park()
        assert cell.parking.angle_deg > 40
        with pytest.raises(PortOutOfReach, match="touch the car"):  # the nearest configuration alone
            plan_plug_in(model, link, cell.flange_from_tip, cell.base_from_port, STANDBY, cell.plug_connector.insertion_depth, PlugInConfig(branches=1))
        plan = plan_plug_in(model, link, cell.flange_from_tip, cell.base_from_port, STANDBY, cell.plug_connector.insertion_depth)
        port_from_base = np.linalg.inv(cell.base_from_port)
        for q in np.vstack([plan.approach, plan.align, plan.insert]):
            origins = np.array([frame[:3, 3] for frame in model.fk(q)])
            assert (origins @ port_from_base[:3, :3].T + port_from_base[:3, 3])[:, 2].min() > 0.05
    finally:
        cell.close()


def test_plan_inputs_are_checked(ur10):
    model, link = ur10
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.9, 0.2]
    with pytest.raises(ConfigError, match="approach"):
        plan_plug_in(model, link, np.eye(4), pose, STANDBY, 0.02, PlugInConfig(approach_distance=0.02))
    with pytest.raises(ValueError, match="finite"):
        plan_plug_in(model, link, np.eye(4), np.full((4, 4), np.nan), STANDBY, 0.02)
    with pytest.raises(ConfigError, match="force_threshold"):
        PlugInConfig(force_threshold=80.0)


def test_a_port_out_of_reach_is_refused_before_any_motion(ur10):
    model, link = ur10
    cell = ChargingCell(ChargingCellConfig(seed=1, camera_scale=0.25, port_nominal=(0.0, 1.9, 0.15)))
    try:
        before = cell.joints
        with pytest.raises(PortOutOfReach, match="out of reach"):
            plan_plug_in(model, link, cell.flange_from_tip, cell.base_from_port, before, cell.plug_connector.insertion_depth)
        outcome = charge(cell, model, link, cell.cameras[0].base_from_camera, plug="type2", standby=STANDBY, flange_from_tip=cell.flange_from_tip)
        assert outcome.status == "refused" and "out of reach" in outcome.reason
        assert np.array_equal(cell.joints, before)
    finally:
        cell.close()


@pytest.mark.parametrize(
    ("config", "expected"),
    [
        ({"port": "type1"}, "does not fit the car's port (type1"),
        ({"camera_target": (1.2, 1.0, 0.9)}, "no charging port in view"),
    ],
)
def test_sessions_that_must_not_start_are_refused(ur10, config, expected):
    model, link = ur10
    cell = ChargingCell(ChargingCellConfig(seed=2, camera_scale=0.5, max_angle_deg=20, **config))
    try:
        before = cell.joints
        outcome = charge(cell, model, link, cell.cameras[0].base_from_camera, plug="type2", standby=STANDBY, flange_from_tip=cell.flange_from_tip)
        assert outcome.status == "refused" and expected in outcome.reason
        assert outcome.result is None and np.array_equal(cell.joints, before)
    finally:
        cell.close()


def test_the_holder_obeys_hookes_law():
    """A steady sideways push on the plug in free space moves it F/k across the tool's
    axis, F/k_axial along it, and the wrist reads the push back."""
    compliance = Compliance(axial=4e4, lateral=4e3, rotational=20.0)
    cell = ChargingCell(ChargingCellConfig(seed=0, camera_scale=0.25, compliance=compliance))
    try:
        cell.set_joints(STANDBY)
        push = np.array([6.0, 0.0, -8.0])  # in the tip frame: across and along the axis
        for _ in range(3000):
            tip = cell.base_from_tip()
            cell.p.applyExternalForce(cell.plug_id, -1, (tip[:3, :3] @ push).tolist(), tip[:3, 3].tolist(), cell.p.WORLD_FRAME)
            reading = cell.servo(STANDBY)
        offset = np.linalg.inv(cell.base_from_tip()) @ cell.base_from_plug()
        assert offset[:3, 3] == pytest.approx(push / [4e3, 4e3, 4e4], rel=0.03, abs=2e-6)
        assert reading == pytest.approx(-push, rel=0.03, abs=0.05)
    finally:
        cell.close()


def test_the_charge_command_writes_its_reports(tmp_path):
    from earcore.app.charge import main

    args = ["--runs", "1", "--seed", "3", "--camera-scale", "0.5", "--max-angle", "20", "--camera-pose", "truth", "--out", str(tmp_path)]
    assert main(args) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    run = summary["per_run"][0]
    assert summary["runs"] == 1 and run["status"] == "plugged" and run["plugged_truth"]
    assert run["peak_force_n"] < summary["force_limit_n"]
    assert (tmp_path / "run-00.png").stat().st_size > 10_000 and (tmp_path / "summary.png").exists()
