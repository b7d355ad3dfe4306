"""The parts images' labels against the scene's geometry: pickup points, grasp axes,
instance masks, depth and the camera pose, and the generator's determinism."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.learning.shards import complete_shards, read_manifest, read_shard, write_manifest
from earcore.sim.part_images import PartImageOptions, PartImageRenderer, generate_shard, manifest_for, plan_shards
from earcore.transforms import rotation_from_quaternion

pytest.importorskip("pybullet")

OPTIONS = PartImageOptions(count=12, width=128, height=96, seed=5, shard_size=6)


@pytest.fixture(scope="module")
def rendered():
    renderer = PartImageRenderer(OPTIONS)
    out = [renderer.render(s) for shard in plan_shards(OPTIONS) for s in shard]
    yield out
    renderer.close()


def test_counts_classes_and_masks(rendered):
    for r in rendered:
        row = r.sample.row
        assert OPTIONS.objects[0] <= row["count"] <= OPTIONS.objects[1] or row["count"] == len(r.placements)
        assert row["count"] == len(r.placements)
        inst = r.sample.images["instances"]
        for i, (pl, body) in enumerate(zip(r.placements, r.bodies)):
            assert OPTIONS.classes[row[f"obj{i}_class"]] == pl.part.name
            # the instance layer is pybullet's segmentation of that body
            assert np.array_equal(inst == i + 1, r.segmentation == body)
            assert row[f"obj{i}_pixels"] == int((inst == i + 1).sum())
        assert inst.max() <= row["count"]


def test_pickup_point_is_the_projected_centre_of_gravity(rendered):
    hits = total = 0
    for r in rendered:
        row, K = r.sample.row, r.K
        camera_from_world = np.linalg.inv(r.world_from_camera)
        for i, pl in enumerate(r.placements):
            pose = pl.world_from_part()
            cog = pose[:3, :3] @ pl.part.centre_of_gravity + pose[:3, 3]
            c = camera_from_world[:3, :3] @ cog + camera_from_world[:3, 3]
            assert [row[f"obj{i}_x"], row[f"obj{i}_y"], row[f"obj{i}_z"]] == pytest.approx(c.tolist(), abs=1e-9)
            u, v = K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]
            assert (row[f"obj{i}_u"], row[f"obj{i}_v"]) == pytest.approx((u, v), abs=1e-9)
            # a part without a vertical bore covers the pixel of its own pickup point
            if not pl.part.round and row[f"obj{i}_pixels"] > 30 and 0 <= u < 127.5 and 0 <= v < 95.5:
                total += 1
                hits += r.sample.images["instances"][int(round(v)), int(round(u))] == i + 1
    assert total > 10 and hits >= 0.95 * total


def test_grasp_axis_follows_the_silhouette(rendered):
    """The labelled axis against the main axis of the part's pixels (elongated parts)."""
    checked = 0
    for r in rendered:
        row = r.sample.row
        for i, pl in enumerate(r.placements):
            if pl.part.round:
                assert row.get(f"obj{i}_axis_u") is None
                continue
            if pl.part.extent[0] < 2.4 * pl.part.extent[1] or row[f"obj{i}_pixels"] < 40:
                continue
            v, u = np.nonzero(r.sample.images["instances"] == i + 1)
            if u.min() == 0 or v.min() == 0 or u.max() == 127 or v.max() == 95:
                continue  # cut by the image border
            d = np.stack([u - u.mean(), v - v.mean()])
            main = np.linalg.eigh(d @ d.T)[1][:, -1]
            axis = np.array([row[f"obj{i}_axis_u"], row[f"obj{i}_axis_v"]])
            angle = np.degrees(np.arccos(min(1.0, abs(float(axis @ main)))))
            assert angle < 12, (pl.part.name, angle)
            checked += 1
    assert checked >= 5


def test_depth_and_camera_pose_put_the_platform_at_z_zero(rendered):
    for r in rendered:
        row = r.sample.row
        world_from_camera = np.eye(4)
        world_from_camera[:3, :3] = rotation_from_quaternion([row["cam_qw"], row["cam_qx"], row["cam_qy"], row["cam_qz"]])
        world_from_camera[:3, 3] = [row["cam_x"], row["cam_y"], row["cam_z"]]
        assert world_from_camera == pytest.approx(r.world_from_camera, abs=1e-9)
        v, u = np.mgrid[0:96, 0:128]
        z = r.true_depth
        pts = np.stack([(u - row["cx"]) / row["fx"] * z, (v - row["cy"]) / row["fy"] * z, z, np.ones_like(z)], -1)
        world = pts @ world_from_camera.T
        # pixels showing a part lie above the platform, below 5 cm (the tallest part is 4.2 cm)
        parts = r.sample.images["instances"] > 0
        assert world[parts][:, 2].min() > -1e-3 and world[parts][:, 2].max() < 0.05
        # the measured depth (mm) is the true depth plus the SR300's noise (σ ~1 mm at 0.5 m)
        measured = r.sample.images["depth"].astype(float) / 1000
        both = (measured > 0) & (z > 0)
        assert both.mean() > 0.9
        assert np.median(np.abs(measured[both] - z[both])) < 0.003


def test_rendering_is_deterministic_and_shards_resume(tmp_path, rendered):
    shards = plan_shards(OPTIONS)
    write_manifest(tmp_path, manifest_for(OPTIONS, shards))
    assert generate_shard(OPTIONS, 1, tmp_path) == 6
    assert complete_shards(tmp_path) == {"shard-00001"}
    manifest = read_manifest(tmp_path)
    assert manifest["kind"] == "parts" and manifest["classes"] == list(OPTIONS.classes)
    shard = read_shard(tmp_path, "shard-00001", 128, 96, samples=6, layers=manifest["layers"])
    for k, r in enumerate(rendered[6:]):
        for layer in ("rgb", "depth", "instances"):
            assert np.array_equal(shard.images[layer][k], r.sample.images[layer])
    assert shard.images["depth"].dtype == np.uint16


def test_placements_do_not_overlap_and_some_touch():
    from earcore.parts.catalogue import PARTS
    from earcore.sim.part_images import _overlap, place_parts

    rng = np.random.default_rng(0)
    touching = 0
    for _ in range(40):
        placed = place_parts(rng, [PARTS[i] for i in rng.integers(0, 13, 8)], np.zeros(2), touching=0.5)
        feet = [p.footprint() for p in placed]
        for i in range(len(feet)):
            for j in range(i):
                assert not _overlap(feet[i], feet[j])
                grown = feet[i] + 0.002 * np.sign(feet[i] - feet[i].mean(0))
                touching += _overlap(grown, feet[j])
    assert touching > 20


def test_options_are_checked():
    from earcore.validate import ConfigError

    with pytest.raises(ConfigError, match="unknown part"):
        PartImageOptions(classes=("M42",)).validate()
    with pytest.raises(ConfigError, match="objects"):
        PartImageOptions(objects=(3, 2)).validate()
