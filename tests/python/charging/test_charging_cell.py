"""The simulated charging cell: parking within its bounds, the stereo pair's geometry,
the port in both cameras' views, the plug on the flange."""

import numpy as np
import pytest

pytest.importorskip("pybullet")

from earcore.errors import ConfigError  # noqa: E402
from earcore.sim.charging_cell import ChargingCell, ChargingCellConfig, _upright_port  # noqa: E402


@pytest.fixture(scope="module")
def cell():
    c = ChargingCell(ChargingCellConfig(seed=2, camera_scale=0.25))
    yield c
    c.close()


def test_parking_stays_within_the_area_and_the_angle(cell):
    config = cell.config
    nominal = np.asarray(config.port_nominal)
    facing = _upright_port(np.asarray(config.rig_position) - nominal)
    rng = np.random.default_rng(3)
    angles = []
    for _ in range(15):
        parking = cell.park(rng)
        centre = parking.base_from_port[:3, 3]
        # inside the square on the car's side, around the nominal place
        offset = centre - nominal
        assert abs(offset @ facing[:, 0]) <= config.parking_area / 2 + 1e-9
        assert abs(offset @ facing[:, 1]) <= config.parking_area / 2 + 1e-9
        assert abs(offset @ facing[:, 2]) < 1e-9
        # the axis' angle to the cameras, measured independently
        to_cameras = np.asarray(config.rig_position) - centre
        axis = parking.base_from_port[:3, 2]
        measured = np.degrees(np.arccos(axis @ to_cameras / np.linalg.norm(to_cameras)))
        assert measured == pytest.approx(parking.angle_deg, abs=1e-6)
        assert 0 <= parking.angle_deg <= config.max_angle_deg
        rotation = parking.base_from_port[:3, :3]
        assert rotation.T @ rotation == pytest.approx(np.eye(3), abs=1e-12)
        angles.append(parking.angle_deg)
    assert max(angles) > 0.5 * config.max_angle_deg  # the range is used


def test_the_stereo_pair_verges_on_the_port(cell):
    rig = cell.rig
    assert rig.baseline == pytest.approx(cell.config.baseline)
    # the right camera turned so the axes cross at the nominal port, on the left one's axis
    left = cell.cameras[0].base_from_camera
    target = np.linalg.inv(left) @ np.r_[cell.config.port_nominal, 1.0]
    assert target[:2] == pytest.approx([0.0, 0.0], abs=1e-9)
    assert rig.vergence_deg == pytest.approx(np.degrees(np.arctan2(cell.config.baseline, target[2])), abs=1e-9)
    port = cell._port_bodies[0]
    for camera in cell.cameras:
        _, depth, segmentation = camera.render_true()
        seen = segmentation == port
        assert seen.sum() > 20  # the arm at stand-by does not hide it
        rows, cols = np.nonzero(seen)
        h, w = segmentation.shape
        assert 0.2 * w < cols.mean() < 0.8 * w and 0.2 * h < rows.mean() < 0.8 * h


def test_the_plug_rides_on_the_flange(cell):
    q = cell.joints.copy()
    q[0] += 0.3
    cell.set_joints(q)
    tip = cell.base_from_tip()
    assert tip == pytest.approx(cell.base_from_flange() @ cell.flange_from_tip)
    body = cell._plug[0]
    position, _ = cell.p.getBasePositionAndOrientation(body)
    assert np.asarray(position) == pytest.approx(tip[:3, 3], abs=1e-6)
    # the pins point along the flange's z
    assert tip[:3, 2] @ cell.base_from_flange()[:3, 2] == pytest.approx(-1.0)


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="colour camera"):
        ChargingCellConfig(sensor="kinect_v2").validate()
    with pytest.raises(ConfigError, match="unknown connector"):
        ChargingCellConfig(port="chademo").validate()
    with pytest.raises(ConfigError, match="edge-on"):
        ChargingCellConfig(max_angle_deg=70).validate()
    with pytest.raises(ConfigError, match="camera_scale"):
        ChargingCellConfig(camera_scale=2.0).validate()


def test_parking_moves_the_truth_and_equation_1_fits_the_pair(cell):
    before = cell.base_from_port
    parking = cell.park(np.random.default_rng(9))
    assert cell.base_from_port == pytest.approx(parking.base_from_port)
    assert np.linalg.norm(cell.base_from_port[:3, 3] - before[:3, 3]) > 1e-3
    # the pair is the paper's: Eq. 1 on noise-free, undistorted pixels of the port's pins
    from earcore.charging.connectors import connector
    from earcore.charging.stereo import verging_triangulation

    rig = cell.rig
    truth = np.linalg.inv(cell.cameras[0].base_from_camera) @ cell.base_from_port
    points = connector("type2").reference_points @ truth[:3, :3].T + truth[:3, 3]
    ideal = type(rig)(rig.K_left, rig.K_right, rig.right_from_left)
    left, right = ideal.project(points)
    estimate = verging_triangulation(left, right, rig.K_left[0, 0], rig.baseline, rig.vergence_deg, (rig.K_left[0, 2], rig.K_left[1, 2]))
    # first order: centimetres at this vergence (17°), where the exact triangulation is exact
    assert np.abs(estimate - points).max() < 0.03
    from earcore.charging.stereo import triangulate

    assert triangulate(ideal, left, right) == pytest.approx(points, abs=1e-9)
