"""Pickup points in the base frame from a segmentation and depth: an analytic box, and
the rendered parts against their labelled centres of gravity."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.parts.locate import PartNotFound, locate_part
from earcore.transforms import axis_angle_matrix


def _looking_down(height: float, yaw: float) -> np.ndarray:
    """base_from_camera of a camera `height` m above the base's origin looking straight
    down (OpenCV axes: z forward = -z of the base), turned by `yaw` about the vertical."""
    down = np.diag([1.0, -1.0, -1.0])
    pose = np.eye(4)
    pose[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, 1.0]), yaw) @ down
    pose[:3, 3] = [0.2, -0.1, height]
    return pose


def test_a_box_on_a_table_by_hand():
    h, w, f = 96, 128, 100.0
    k = (f, f, 64.0, 48.0)
    pose = _looking_down(0.5, 0.3)
    depth = np.full((h, w), 0.5)  # the table at base z = 0
    belief = np.zeros((h, w))
    belief[40:50, 60:80] = 1.0  # a 2 cm tall box's top face
    depth[40:50, 60:80] = 0.48
    pick = locate_part(belief, depth, k, pose)
    # the top face's centre pixel (69.5, 44.5) at 0.48 m, back into the base frame
    centre = np.array([(69.5 - 64) / f * 0.48, (44.5 - 48) / f * 0.48, 0.48])
    expected = pose[:3, :3] @ centre + pose[:3, 3]
    assert pick.pixel == pytest.approx((69.5, 44.5))
    assert pick.height == pytest.approx(0.02, abs=1e-9)
    assert pick.base[:2] == pytest.approx(expected[:2], abs=1e-9)
    assert pick.base[2] == pytest.approx(0.01, abs=1e-9)  # half the box's height
    assert pick.pixels == 200
    with pytest.raises(PartNotFound):
        locate_part(np.zeros((h, w)), depth, k, pose)
    with pytest.raises(PartNotFound, match="support"):
        locate_part(np.ones((h, w)), depth, k, pose)
    with pytest.raises(ValueError, match="4x4"):
        locate_part(belief, depth, k, np.eye(3))


def test_rendered_parts_are_located_within_a_centimetre():
    pytest.importorskip("pybullet")
    from earcore.sim.part_images import PartImageOptions, PartImageRenderer, plan_shards

    options = PartImageOptions(count=8, width=128, height=96, seed=21, shard_size=8)
    renderer = PartImageRenderer(options)
    errors = []
    try:
        for s in plan_shards(options)[0]:
            r = renderer.render(s)
            row, inst = r.sample.row, r.sample.images["instances"]
            k = (row["fx"], row["fy"], row["cx"], row["cy"])
            for i in range(row["count"]):
                mask = inst == i + 1
                if mask.sum() < 20 or mask[[0, -1]].any() or mask[:, [0, -1]].any():  # seen whole
                    continue
                pick = locate_part(mask.astype(float), r.sample.images["depth"] / 1000.0, k, r.world_from_camera)
                truth = r.world_from_camera @ np.array([row[f"obj{i}_x"], row[f"obj{i}_y"], row[f"obj{i}_z"], 1.0])
                errors.append(np.linalg.norm(pick.base - truth[:3]))
    finally:
        renderer.close()
    # with the true segmentation, the measured (noisy) depth and the camera's pose as its calibration
    assert len(errors) > 20
    assert np.median(errors) < 0.01


def test_regions_agree_with_scipy():
    from scipy import ndimage

    from earcore.parts.locate import label_regions

    rng = np.random.default_rng(3)
    for _ in range(100):
        mask = rng.random((int(rng.integers(1, 40)), int(rng.integers(1, 40)))) < rng.uniform(0.1, 0.9)
        labels, count = label_regions(mask)
        reference, expected = ndimage.label(mask)  # 4-connected by default
        assert count == expected
        assert ((labels > 0) == mask).all()
        # the same partition: each of ours is exactly one of scipy's
        assert len(set(zip(labels[mask].tolist(), reference[mask].tolist()))) == count
        # numbered in the order of their first pixel
        firsts = [int(np.flatnonzero(labels.ravel() == k)[0]) for k in range(1, count + 1)]
        assert firsts == sorted(firsts)
    snake = np.zeros((40, 40), bool)
    snake[::2] = True
    snake[1::4, -1] = True
    snake[3::4, 0] = True
    assert label_regions(snake)[1] == 1
    with pytest.raises(ValueError, match="H, W"):
        label_regions(np.zeros(5, bool))


def test_every_region_is_located_apart():
    from earcore.parts.locate import locate_parts

    h, w, f = 96, 128, 100.0
    k = (f, f, 64.0, 48.0)
    pose = _looking_down(0.5, -0.4)
    depth = np.full((h, w), 0.5)
    belief = np.zeros((h, w))
    belief[10:20, 10:30] = 0.9  # box A, 200 px
    belief[60:70, 90:100] = 0.8  # box B, 100 px
    belief[40:42, 60:62] = 0.9  # 4 px: below min_pixels
    depth[belief > 0] = 0.47
    picks = locate_parts(belief, depth, k, pose, min_pixels=12)
    assert [p.pixels for p, _ in picks] == [200, 100]  # the biggest first
    for (pick, region), box in zip(picks, [(slice(10, 20), slice(10, 30)), (slice(60, 70), slice(90, 100))]):
        alone = np.zeros((h, w))
        alone[box] = belief[box]
        expected = locate_part(alone, depth, k, pose)
        assert pick.base == pytest.approx(expected.base, abs=1e-12)
        assert region.sum() == pick.pixels and region[box].all()
    belief[20:60, 20:22] = 0.9  # a bridge from A down to row 60: still two regions of 12 px or more
    depth[belief > 0] = 0.47
    assert len(locate_parts(belief, depth, k, pose, min_pixels=12)) == 2


def test_neighbouring_parts_are_not_the_support():
    from earcore.parts.locate import locate_parts

    h, w, f = 48, 64, 100.0
    k = (f, f, 32.0, 24.0)
    pose = _looking_down(0.5, 0.0)
    depth = np.full((h, w), 0.5)  # the table, base z = 0
    belief = np.zeros((h, w))
    belief[20:26, 20:26] = 1.0  # a 1 cm part ...
    depth[20:26, 20:26] = 0.49
    for rows, cols in ((slice(14, 19), slice(14, 32)), (slice(27, 32), slice(14, 32)), (slice(19, 27), slice(14, 19)), (slice(19, 27), slice(27, 32))):
        belief[rows, cols] = 1.0  # ... ringed 1 px away by a 3 cm part of the same type
        depth[rows, cols] = 0.47
    small = next(p for p, region in locate_parts(belief, depth, k, pose, min_pixels=12) if region[22, 22])
    assert small.height == pytest.approx(0.01, abs=1e-9)  # the table shows in the 1 px gap, the neighbour does not count
    assert small.base[2] == pytest.approx(0.005, abs=1e-9)
