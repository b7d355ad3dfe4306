"""The station's calibration without markers: from the plug's pins in poses the robot
picks, the left camera's pose and the plug's tip on the flange, against the
simulation's truth."""

from __future__ import annotations

import numpy as np
import pytest

from earcore import robots
from earcore.app.charge_calibration import CalibrationFailed, MarkerlessConfig, calibrate_markerless, workspace_error_mm
from earcore.sim.charging_cell import ChargingCell, ChargingCellConfig
from earcore.transforms import pose_from_vector, rotation_angle

pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def station():
    cell = ChargingCell(ChargingCellConfig(seed=11, camera_scale=0.5))
    cell.drive_away()
    robot = robots.load("ur10")
    yield cell, robot, robot.link_names.index(robots.FLANGES["ur10"][0])
    cell.close()


def test_markerless_calibration_finds_the_camera_and_the_plug(station):
    cell, robot, link = station
    true_camera, true_tip = cell.cameras[0].base_from_camera, cell.flange_from_tip
    # the installation's drawing: 5.4 cm and 1.8° off; the holder as designed: 3.3 cm and 0.3° off
    rough_camera = true_camera @ pose_from_vector([0.03, -0.04, 0.02, 0.02, -0.015, 0.018])
    rough_tip = true_tip @ pose_from_vector([0.02, -0.025, 0.01, 0.003, -0.003, 0.002])
    start = cell.joints
    result = calibrate_markerless(cell, robot, link, cell.plug_connector, rough_camera, rough_tip, MarkerlessConfig(poses=20, seed=1))
    assert result.tried <= 20 and result.used >= 8 and len(result.discarded) == result.tried - result.used
    assert np.array_equal(cell.joints, start)
    # acceptance: the camera within 1.5 mm over the workspace, the tip within 1 mm
    assert workspace_error_mm(result.base_from_camera, true_camera, cell.base_from_port[:3, 3]) < 1.5
    assert np.linalg.norm(result.flange_from_tip[:3, 3] - true_tip[:3, 3]) < 0.001
    assert np.degrees(rotation_angle(result.flange_from_tip, true_tip)) < 0.5
    assert result.rmse_mm < 1.0


def test_a_camera_that_never_sees_the_plug_fails_clearly(station):
    cell, robot, link = station
    # the camera believed to look the other way: the plug goes where no camera sees it
    away = cell.cameras[0].base_from_camera @ pose_from_vector([0.0, 0.0, 0.0, 0.0, np.pi, 0.0])
    with pytest.raises(CalibrationFailed, match="poses showed the plug"):
        calibrate_markerless(cell, robot, link, cell.plug_connector, away, cell.flange_from_tip, MarkerlessConfig(poses=6, min_good=4))


def test_the_workspace_error_is_the_mean_displacement():
    truth = np.eye(4)
    shifted = truth.copy()
    shifted[:3, 3] = [0.003, 0.0, 0.004]  # a pure shift moves every point by 5 mm
    assert workspace_error_mm(shifted, truth, np.zeros(3)) == pytest.approx(5.0)
    turned = pose_from_vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.001])  # 1 mrad about z through the camera
    # a point at distance r from the axis moves r·1 mrad: the cube 1 m off the axis, ±0.25 m
    error = workspace_error_mm(turned, truth, np.array([1.0, 0.0, 0.0]))
    g = np.linspace(-0.25, 0.25, 5)
    x, y = np.meshgrid(1.0 + g, g, indexing="ij")
    assert error == pytest.approx(np.hypot(x, y).mean() * 1.0, rel=1e-3)
