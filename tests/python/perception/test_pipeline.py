"""The perception loop's stages in the cell: far rays clearing the crop sphere, ICP refinement of perturbed cameras, a constant pose error."""

from __future__ import annotations

import numpy as np
import pytest

pybullet = pytest.importorskip("pybullet")

import earcore  # noqa: E402
from earcore.synthetic import look_at  # noqa: E402


def test_far_ray_selection_helpers():
    """The far rays' pixel grid is every stride-th row and column (stride = width /
    FAR_RAYS_ACROSS, rounded); membership in the crop's ascending index by binary
    search equals np.isin, empty index included."""
    from earcore.perception.pipeline import FAR_RAYS_ACROSS, _in_sorted, _pixel_grid

    for shape in ((424, 512), (120, 160), (7, 3)):
        height, width = shape
        stride = max(1, round(width / FAR_RAYS_ACROSS))
        pixels = np.arange(height * width)
        want = ((pixels % width) % stride == 0) & ((pixels // width) % stride == 0)
        np.testing.assert_array_equal(_pixel_grid(shape), want)
    rng = np.random.default_rng(4)
    values = np.unique(rng.integers(0, 1000, 300))
    queries = rng.integers(-5, 1010, 500)
    np.testing.assert_array_equal(_in_sorted(values, queries), np.isin(queries, values))
    assert not _in_sorted(values[:0], queries).any()




def test_icp_refinement_aligns_perturbed_cameras():
    """Paper II's one-off fine alignment in the loop: fixed cameras 2 cm / 1° off come
    out better aligned to each other (relative poses; 5.3 → 2.9 cm here)."""
    from earcore.perception import PerceptionConfig, PerceptionPipeline
    from earcore.sim.cell import SimulatedCell
    from earcore.sim.config import CellConfig
    from earcore.transforms import perturb_pose

    config = CellConfig()
    config.cameras = [c for c in config.cameras if c.mount == "world"]
    config.person.enabled = False
    cell = SimulatedCell(config)
    cell.step()
    frames = cell.capture()
    cell.close()
    truth = {f.camera: f.base_from_camera for f in frames}
    pipeline = PerceptionPipeline(PerceptionConfig(refine_poses=True), cell.model, fixed_cameras=set(truth))
    rng = np.random.default_rng(3)
    for name, pose in truth.items():
        pipeline.set_pose(name, perturb_pose(pose, 0.02, np.radians(1.0), rng))
    before = {n: p.copy() for n, p in pipeline.poses.items()}
    pipeline.process(frames, cell.q, 0.0)

    def relative_error(poses):
        ref, errors = frames[0].camera, []
        for name in truth:
            if name != ref:
                est = np.linalg.inv(poses[ref]) @ poses[name]
                true = np.linalg.inv(truth[ref]) @ truth[name]
                errors.append(np.linalg.norm(est[:3, 3] - true[:3, 3]))
        return max(errors)

    assert relative_error(before) > 0.03
    assert relative_error(pipeline.poses) < 0.6 * relative_error(before)


def test_pose_error_is_a_constant_calibration_error():
    from earcore.interfaces import Frame
    from earcore.perception import PerceptionPipeline
    from earcore.perception.config import PerceptionConfig

    pipeline = PerceptionPipeline(PerceptionConfig(pose_error=(0.02, 0.01)), earcore.robots.load("ur5"), fixed_cameras={"a"})
    pose = look_at([1.5, 1.5, 1.0], [0, 0, 0])
    frame = Frame("a", 0.0, np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4)), np.eye(3), pose)
    first = pipeline.camera_pose(frame)
    assert np.linalg.norm(first[:3, 3] - pose[:3, 3]) == pytest.approx(0.02)
    assert np.array_equal(pipeline.camera_pose(frame), first)
    moving = Frame("wrist", 0.0, frame.colour, frame.depth, frame.K, pose)
    assert np.array_equal(pipeline.camera_pose(moving), pose)
