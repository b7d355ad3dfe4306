"""Shape-based matching of the port on rendered images of the charging cell: the
reference points against the truth's projection, the score separating the right model
from a wrong one, and the projection against OpenCV's."""

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("pybullet")

from earcore.charging.connectors import connector  # noqa: E402
from earcore.charging.locate import locate  # noqa: E402
from earcore.charging.matching import ShapeModel, find, project_points  # noqa: E402
from earcore.sim.charging_cell import ChargingCell, ChargingCellConfig  # noqa: E402
from earcore.transforms import rotation_angle  # noqa: E402


def test_projection_matches_opencv():
    rng = np.random.default_rng(0)
    K = np.array([[900.0, 0.0, 611.5], [0.0, 905.0, 511.5], [0.0, 0.0, 1.0]])
    dist = np.array([-0.08, 0.03, 0.001, -0.0005, 0.002])
    points = np.c_[rng.uniform(-0.5, 0.5, (40, 2)), rng.uniform(1.0, 3.0, 40)]
    theirs = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    assert project_points(points, K, dist) == pytest.approx(theirs, abs=1e-9)


def test_models_hold_the_connectors_geometry():
    k = connector("type2")
    port = ShapeModel.port(k)
    assert port.outer_radius == pytest.approx(np.linalg.norm(port.points[port.outer, :2], axis=1).max(), rel=1e-6)
    assert port.reference == pytest.approx(k.reference_points)
    plug = ShapeModel.plug(k)
    # the plug's model frame faces the viewer: back in the tip frame the pins' tips are at −pin_length
    tips = plug.reference @ plug.object_from_model[:3, :3].T
    assert tips[:, 2] == pytest.approx(-k.pin_length)
    assert tips[:, :2] == pytest.approx(k.reference_points[:, :2])


@pytest.fixture(scope="module")
def scenes():
    cell = ChargingCell(ChargingCellConfig(seed=4))  # the cameras at their own resolution: the port is ~170 px across
    rng = np.random.default_rng(11)
    out = []
    for i in range(3):
        parking = cell.park(rng) if i else cell.parking
        out.append((parking, *cell.capture()))
    yield cell, out
    cell.close()


def test_the_port_is_found_where_it_is(scenes):
    cell, shots = scenes
    k = connector("type2")
    model = ShapeModel.port(k)
    rig = cell.rig
    for parking, left, right in shots:
        truth = np.linalg.inv(cell.cameras[0].base_from_camera) @ parking.base_from_port
        estimate = locate(left, right, model, rig)
        assert estimate is not None and not estimate.flagged, estimate and estimate.reasons
        # the chosen matches put the pins where the truth projects them (half resolution)
        for match, pose in zip(estimate.matches, (truth, rig.right_from_left @ truth)):
            expected = project_points(k.reference_points @ pose[:3, :3].T + pose[:3, 3], rig.K_left, rig.dist_left)
            assert np.abs(match.reference_pixels - expected).max() < 1.5, parking.angle_deg
            assert match.score > 0.55
        # both routes: the paper's (pins triangulated, plane, layout) and both images at once
        for pose in (estimate.paper, estimate.camera_from_port):
            assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.002
            assert np.degrees(rotation_angle(pose[:3, :3], truth[:3, :3])) < 2.0
        assert estimate.fit_mm < 0.5


def test_a_wrong_model_scores_lower_and_an_empty_scene_finds_nothing(scenes):
    cell, shots = scenes
    rig = cell.rig
    _, left, _ = shots[0]
    right_model = find(left, ShapeModel.port(connector("type2")), rig.K_left, rig.dist_left)
    wrong_model = find(left, ShapeModel.port(connector("type1")), rig.K_left, rig.dist_left)
    assert right_model is not None
    # the outer circles are alike; what lies inside them tells the types apart
    assert wrong_model is None or wrong_model.inner_score < right_model.inner_score - 0.1
    blank = np.full_like(left, 128)
    assert find(blank, ShapeModel.port(connector("type2")), rig.K_left, rig.dist_left) is None
    assert locate(blank, blank, ShapeModel.port(connector("type2")), rig) is None
    with pytest.raises(ValueError, match="8-bit"):
        find(left.astype(np.float32) / 255, ShapeModel.port(connector("type2")), rig.K_left, rig.dist_left)
