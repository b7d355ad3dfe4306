"""The main job's pose network: the truth it compares with is the robot's joints as
pybullet places them, the estimates land in the summary and a picture, and a camera
that is not in the cell is refused."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pybullet = pytest.importorskip("pybullet")
pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")

from earcore.app.run import run  # noqa: E402
from earcore.errors import ConfigError  # noqa: E402
from earcore.learning import png  # noqa: E402
from earcore.pose.overlay import GREEN  # noqa: E402
from earcore.sim.cell import SimulatedCell  # noqa: E402
from earcore.sim.config import CellConfig, PersonConfig  # noqa: E402
from earcore.sim.robot_images import keypoint_frames, keypoint_positions, revolute_joints  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "pose"))
from test_estimate_onnx import exported  # noqa: E402
from test_run import small_run_config  # noqa: E402


@pytest.mark.parametrize("robot", ["ur5", "iiwa"])
def test_truth_is_where_pybullet_puts_the_joints(robot):
    cell = SimulatedCell(CellConfig(robot=robot, cameras=[], person=PersonConfig(enabled=False)))
    try:
        rng = np.random.default_rng(3)
        names, links = revolute_joints(cell.model, robot)
        for q in cell.model.random_configurations(3, seed=int(rng.integers(1000))):
            cell.q = q
            cell._apply_joints()
            ours = keypoint_positions(cell.model, keypoint_frames(cell.model, robot), q)
            for i, link in enumerate(links):
                state = cell.p.getLinkState(cell.robot_id, cell.link_ids[cell.model.link_names[link]], computeForwardKinematics=True)
                assert np.allclose(ours[i], state[4], atol=1e-5), (robot, names[i])
    finally:
        cell.close()


def known_as(weights: Path, robots: list[str]) -> None:
    """The exported toy network's sidecar naming other robots (its weights know none)."""
    import json

    sidecar = weights.with_suffix(".json")
    data = json.loads(sidecar.read_text())
    data["robots"] = robots
    sidecar.write_text(json.dumps(data))


def test_main_job_reports_pose_estimates_and_draws_them(tmp_path):
    _, weights = exported(tmp_path, "multi")
    known_as(weights, ["ur5", "ur3"])  # the cell's robot: the run compares its keypoints
    config = small_run_config(1.0)
    config.cell.renderer = "pybullet"
    config.pose.camera = "kinect_v2_left"
    config.pose.weights = str(weights)
    config.pose.rate_hz = 2.0
    summary = run(config, tmp_path / "out", progress=False, record=False)
    pose = summary["pose"]
    assert pose["camera"] == "kinect_v2_left" and pose["estimates"] in (2, 3)
    assert np.isfinite(pose["joints_median_cm"]) and pose["joints_median_cm"] > 0
    picture = png.read(tmp_path / "out" / "pose.png")
    # The robot is in this camera's view: its true joints are drawn as green crosses.
    assert picture.ndim == 3 and (picture == GREEN).all(axis=2).sum() >= 10


def test_a_pose_camera_outside_the_cell_is_refused():
    config = small_run_config(1.0)
    config.pose.camera = "nowhere"
    with pytest.raises(ConfigError, match="nowhere.*kinect_v2_left"):
        config.validate()


def test_a_pose_camera_needs_pybullets_renderer():
    config = small_run_config(1.0)
    config.pose.camera = "kinect_v2_left"
    with pytest.raises(ConfigError, match='renderer = "pybullet"'):
        config.validate()
    config.cell.renderer = "pybullet"
    config.validate()


def test_a_network_that_does_not_know_the_cells_robot_is_refused(tmp_path):
    """Its keypoints would be compared with another robot's (76 cm 'errors' for a Panda
    against a network of URs): refused before the run, naming what it knows."""
    from earcore.app.pose_watch import PoseWatch
    from earcore.pose.inference import load_model

    _, weights = exported(tmp_path, "multi")
    config = small_run_config(1.0)
    config.pose.camera = "kinect_v2_left"
    config.pose.weights = str(weights)
    known = list(load_model(str(weights)).sidecar["robots"])
    PoseWatch(config.pose, known[0])
    with pytest.raises(ConfigError, match=f"the network knows {known[0]}.*not the cell's 'panda'"):
        PoseWatch(config.pose, "panda")
