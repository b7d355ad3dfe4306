"""The parts station in the cell: its views in the robot's base frame, the calibration
error model, and `earcore parts show` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from earcore.sim.part_station import BASE_FROM_PLATFORM, calibrated_pose

pytest.importorskip("pybullet")


def _back_project(view, mask):
    fx, fy, cx, cy = view.intrinsics
    v, u = np.nonzero(mask & (view.depth_mm > 0))
    z = view.depth_m[v, u]
    camera = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], 1)
    pose = view.base_from_camera
    return camera @ pose[:3, :3].T + pose[:3, 3]


def test_views_are_in_the_base_frame():
    from earcore.parts.locate import locate_parts
    from earcore.sim.part_station import PartStation

    errors = []
    with PartStation(seed=4) as station:
        for index in range(4):
            view = station.view(index)
            assert view.rgb.shape == (96, 128, 3) and view.depth_mm.shape == (96, 128)
            # the platform is the table top (z = 0 of the base frame) in front of the robot
            ground = _back_project(view, view.instances == 0)
            near = np.abs(ground[:, 0] - BASE_FROM_PLATFORM[0, 3]) < 0.25
            assert abs(np.median(ground[near, 2])) < 0.004
            assert (np.abs(view.centres[:, :2] - BASE_FROM_PLATFORM[:2, 3]) < 0.35).all()
            assert ((view.centres[:, 2] > 0) & (view.centres[:, 2] < 0.05)).all()
            # an oracle segmentation per type, located through the view's pose, lands on the centres
            for cls in np.unique(view.classes):
                slots = np.flatnonzero(view.classes == cls)
                belief = np.isin(view.instances, slots + 1).astype(float)
                for pick, region in locate_parts(belief, view.depth_m, view.intrinsics, view.base_from_camera):
                    inside = [i for i in slots if (region & (view.instances == i + 1)).sum() > 0.5 * (view.instances == i + 1).sum()]
                    if len(inside) == 1:
                        errors.append(np.linalg.norm(pick.base - view.centres[inside[0]]))
    assert len(errors) > 10 and np.median(errors) < 0.01


def test_a_calibration_error_moves_and_turns_by_its_size():
    rng = np.random.default_rng(0)
    pose = np.eye(4)
    pose[:3, 3] = [0.4, 0.1, 0.5]
    for _ in range(5):
        moved = calibrated_pose(pose, 1.5, 0.06, rng)
        assert np.linalg.norm(moved[:3, 3] - pose[:3, 3]) == pytest.approx(0.0015)
        angle = np.degrees(np.arccos(np.clip((np.trace(moved[:3, :3] @ pose[:3, :3].T) - 1) / 2, -1, 1)))
        assert angle == pytest.approx(0.06, abs=1e-4)
    assert np.array_equal(calibrated_pose(pose, 0.0, 0.0, rng), pose)


def test_show_command(tmp_path, capsys):
    from earcore.app.parts import main
    from earcore.learning import png

    data, run, out = tmp_path / "parts", tmp_path / "run", tmp_path / "show"
    assert main(["generate", "--out", str(data), "--count", "16", "--size", "64x48", "--seed", "2", "--workers", "1", "--quiet"]) == 0
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "2", "--batch", "4", "--option", "widths=[4,8,8,8]", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["show", "--model", str(run), "--part", "M20", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    summary = json.loads((out / "show.json").read_text())
    assert summary["network"] == "detector" and summary["part"] == "M20" and summary["parts_of_type"] >= 1  # the first view showing one
    assert f"{len(summary['picks'])} found" in text
    for pick in summary["picks"]:
        assert len(pick["base_m"]) == 3 and pick["pixels"] >= 12
    assert png.read(out / "show.png").shape == (4 * 48, 4 * 64, 3)
    assert main(["show", "--model", str(run), "--part", "Bolt"]) == 2
    assert main(["show", "--model", str(run), "--needle-part", "M20"]) == 2
    assert main(["show", "--model", str(tmp_path / "nothing"), "--part", "M20"]) == 1
