"""SurfaceMap (NOctoSLAM): leaf blending, bottom-up propagation, plane normals."""

from __future__ import annotations

import numpy as np
import pytest

import earcore


def prob(log_odds: float) -> float:
    return 1.0 - 1.0 / (1.0 + np.exp(log_odds))


def test_leaf_positions_blend_by_occupancy_and_sensor_model():
    m = earcore.SurfaceMap(0.1)
    pts = np.array([[0.01, 0.02, 0.03], [0.09, 0.05, 0.01], [0.05, 0.08, 0.07]])
    m.insert(pts[:1])
    m.insert(pts[1:])  # same leaf, blended in input order
    expected, log_odds, hit = pts[0].copy(), np.float32(0.0), np.float32(np.log(0.7 / 0.3))
    for i, d in enumerate(pts):
        if i == 0:
            expected = d.copy()
        else:
            p = prob(log_odds)
            expected = (expected * p + d * 0.7) / (p + 0.7)
        log_odds = np.float32(log_odds + hit)
    positions, normals, depths = m.nodes(16)
    assert len(positions) == 1 and depths[0] == 16
    np.testing.assert_allclose(positions[0], expected, atol=1e-6)
    assert np.isnan(normals[0]).all(), "a single point has no normal"


def test_inner_nodes_hold_the_mean_of_their_children():
    rng = np.random.default_rng(2)
    m = earcore.SurfaceMap(0.05)
    m.insert(rng.uniform(-1, 1, (4000, 3)))
    m.insert(rng.uniform(-1, 1, (4000, 3)))
    leaves, _, _ = m.nodes(16)
    parents, _, _ = m.nodes(15)
    # Blended positions stay inside their voxels, so a parent's cube groups its children.
    def group(p, size):
        return [tuple(k) for k in np.floor(p / size).astype(np.int64)]

    child_groups: dict = {}
    for key, p in zip(group(leaves, 0.1), leaves):
        child_groups.setdefault(key, []).append(p)
    assert len(parents) == len(child_groups)
    for key, p in zip(group(parents, 0.1), parents):
        np.testing.assert_allclose(p, np.mean(child_groups[key], axis=0), atol=1e-5)


def test_plane_normals_appear_at_inner_nodes():
    rng = np.random.default_rng(4)
    n = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    ab = rng.uniform(-1, 1, (60_000, 2))
    plane = 0.7 * n + ab[:, :1] * u + ab[:, 1:] * v
    m = earcore.SurfaceMap(0.02)
    m.insert(plane)
    for depth in (13, 14):
        _, normals, _ = m.nodes(depth)
        have = ~np.isnan(normals[:, 0])
        assert have.mean() > 0.8, f"most nodes at depth {depth} should have a normal"
        angles = np.degrees(np.arccos(np.clip(np.abs(normals[have] @ n), 0, 1)))
        assert np.median(angles) < 3.0 and np.percentile(angles, 90) < 10.0


def test_an_update_touches_only_its_branch():
    m = earcore.SurfaceMap(0.05)
    rng = np.random.default_rng(9)
    m.insert(rng.uniform([-1, -1, 0], [-0.2, 1, 1], (5000, 3)))
    far_before = m.nodes()
    touched = m.insert(rng.uniform([2.0, 2.0, 0], [2.4, 2.4, 0.4], (3000, 3)))
    assert touched > 0
    after = m.nodes()
    # Every node from before is unchanged (the root and the nodes above both regions
    # excepted): compare the nodes whose positions lie in the first region.
    def region(nodes):
        pos, nor, dep = nodes
        keep = (pos[:, 0] < -0.19) & (dep >= 4)
        order = np.lexsort((dep[keep], pos[keep, 2], pos[keep, 1], pos[keep, 0]))
        return pos[keep][order], nor[keep][order]

    np.testing.assert_array_equal(region(far_before)[0], region(after)[0])
    np.testing.assert_array_equal(region(far_before)[1], region(after)[1])


def test_surface_map_rejects_bad_input():
    with pytest.raises(ValueError):
        earcore.SurfaceMap(0.0)
    with pytest.raises(ValueError):
        earcore.SurfaceMap(0.05, similar=2.0)
    m = earcore.SurfaceMap(0.05)
    with pytest.raises(ValueError, match="not finite"):
        m.insert([[0.0, np.nan, 0.0]])
    with pytest.raises(earcore.OutOfMapError):
        m.insert([[1e6, 0.0, 0.0]])
    with pytest.raises(ValueError):
        m.nodes(17)
    assert m.size() == 0 and m.insert(np.zeros((0, 3))) == 0


def test_lidar_scans_of_the_room_register_against_the_surface_map():
    """The NOctoSLAM setting in miniature: a VLP-16-like scan of the 8 × 8 × 3.5 m room
    builds the map; the next scan, taken 5 cm / 1° further on, registers against it."""
    rng = np.random.default_rng(11)
    boxes = earcore.synthetic.lidar_room(rng)
    first = np.eye(4)  # sensor z axis up, as a lidar is mounted
    first[:3, 3] = [0.2, -0.3, 1.5]
    scan = earcore.synthetic.render_lidar_scan(first, [], boxes, seed=1)
    assert 14_000 <= len(scan) <= 15_040
    surface = earcore.SurfaceMap(0.05)
    surface.insert(scan @ first[:3, :3].T + first[:3, 3])
    c, s = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
    step = np.eye(4)
    step[:2, :2] = [[c, -s], [s, c]]
    step[:3, 3] = [0.04, 0.03, 0.0]
    second = step @ first
    scan2 = earcore.synthetic.render_lidar_scan(second, [], boxes, seed=2)
    result = earcore.icp_point_to_plane(scan2, surface, first, max_correspondence_distance=0.5)
    error = np.linalg.inv(second) @ result.transform
    assert np.linalg.norm(error[:3, 3]) < 0.02
    assert np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1))) < 0.3


def leaves(m: earcore.SurfaceMap):
    return m.nodes(leaves_only=True)


def test_dynamic_leaf_depth_sizes_leaves_to_the_gap_between_scan_lines():
    """A point at range r with scan lines b radians apart ends in the smallest node of
    at least r·b: at 1 cm resolution and 2°, r = 2 m gives 6.98 cm → 8 cm leaves
    (depth 13), r = 0.2 m gives 0.7 cm → 1 cm leaves (depth 16), r = 9 m is capped at
    16 cm (depth 12). Each leaf holds the mean of its points (position_memory above
    the count), grouped here by flooring coordinates to the leaf size."""
    rng = np.random.default_rng(5)
    origin = np.array([0.013, -0.021, 0.017])
    spacing = np.radians(2.0)
    for r, size, depth in ((2.0, 0.08, 13), (0.2, 0.01, 16), (9.0, 0.16, 12)):
        m = earcore.SurfaceMap(0.01, position_memory=1000)
        directions = rng.normal(size=(3000, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        pts = origin + r * directions
        m.insert(pts, origin, spacing, max_leaf_size=0.16)
        positions, _, depths = leaves(m)
        assert set(depths.tolist()) == {depth}, (r, set(depths.tolist()))
        groups: dict = {}
        for cell, p in zip(map(tuple, np.floor(pts / size).astype(np.int64)), pts):
            groups.setdefault(cell, []).append(p)
        assert len(positions) == len(groups)
        expected = np.array([np.mean(g, axis=0) for g in groups.values()])
        # Match each leaf with its group by cell.
        got = {tuple(np.floor(p / size).astype(np.int64)): p for p in positions}
        for cell, mean in zip(groups, expected):
            np.testing.assert_allclose(got[cell], mean, atol=2e-6)


def test_coarse_leaves_absorb_finer_points_and_fine_branches_take_coarse_ones():
    origin = np.zeros(3)
    far = np.array([[3.01, 0.52, 0.33]])  # 3 m: a 16 cm leaf at 2°
    m = earcore.SurfaceMap(0.01)
    m.insert(far, origin, np.radians(2.0), max_leaf_size=0.16)
    m.insert(far + 0.004)  # a finest-level point in the same 16 cm cell
    positions, _, depths = leaves(m)
    assert depths.tolist() == [12] and len(positions) == 1

    fine = earcore.SurfaceMap(0.01)
    fine.insert(far)
    fine.insert(far + 0.003, origin, np.radians(2.0), max_leaf_size=0.16)
    positions, _, depths = leaves(fine)
    assert depths.tolist() == [16] and len(positions) == 1, "the coarse point joins the existing fine leaf"


def test_position_memory_averages_the_first_points_then_moves_slowly():
    pts = np.random.default_rng(8).uniform(0.0, 0.1, (12, 3))
    m = earcore.SurfaceMap(0.1, position_memory=4)
    for p in pts:
        m.insert(p[None])
    expected = pts[0].copy()
    for i, p in enumerate(pts[1:], start=1):
        w = min(i, 4)
        expected = (expected * w + p) / (w + 1)
    positions, _, _ = m.nodes(16)
    np.testing.assert_allclose(positions[0], expected, atol=1e-6)
    # A whole batch blends in input order, as one point at a time does.
    batch = earcore.SurfaceMap(0.1, position_memory=4)
    assert batch.insert(pts) == 1
    np.testing.assert_allclose(batch.nodes(16)[0][0], expected, atol=1e-6)
    # With memory for all of them the leaf is their mean.
    mean = earcore.SurfaceMap(0.1, position_memory=100)
    mean.insert(pts)
    np.testing.assert_allclose(mean.nodes(16)[0][0], pts.mean(axis=0), atol=1e-6)


def test_dynamic_leaf_depth_rejects_bad_input():
    m = earcore.SurfaceMap(0.01)
    pts = np.ones((5, 3))
    with pytest.raises(ValueError, match="both"):
        m.insert(pts, sensor_origin=[0, 0, 0])
    with pytest.raises(ValueError, match="beam_spacing"):
        m.insert(pts, [0, 0, 0], -0.1)
    with pytest.raises(ValueError, match="origin"):
        m.insert(pts, [np.nan, 0, 0], 0.03)
    with pytest.raises(ValueError, match="max_leaf_size"):
        m.insert(pts, [0, 0, 0], 0.03, max_leaf_size=0.0)
    with pytest.raises(ValueError):
        earcore.SurfaceMap(0.01, position_memory=0)
    assert m.size() == 0


def test_lidar_odometry_follows_a_hand_held_scanner_through_the_room():
    """NOctoSLAM's loop in short (the full 15 episodes: benches/noctoslam_reproduction.py):
    4 s of a VLP-16-like lidar (σ 1.5 cm) carried at 0.5 m/s through the room, registered
    scan to map. Errors against the simulated ground truth stay within the paper's
    whole-episode means (0.029 m, 0.019 rad) at every scan."""
    from earcore.lidar_odometry import LidarOdometry

    rng = np.random.default_rng(21)
    boxes = earcore.synthetic.lidar_room(rng)
    truths = earcore.synthetic.handheld_trajectory(rng, seconds=4.0)
    odometry = LidarOdometry(initial_pose=truths[0])
    position, rotation = [], []
    for k, truth in enumerate(truths):
        scan = earcore.synthetic.render_lidar_scan(truth, [], boxes, noise_sigma=0.015, seed=k)
        error = np.linalg.inv(truth) @ odometry.add_scan(scan)
        position.append(np.linalg.norm(error[:3, 3]))
        rotation.append(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert np.mean(position) < 0.029 and np.mean(rotation) < 0.019, (np.mean(position), np.mean(rotation))
    assert max(position) < 0.05 and max(rotation) < np.radians(1.0), (max(position), max(rotation))
    assert odometry.degenerate_scans == 0 and len(odometry.poses) == len(truths) == 80
    with pytest.raises(ValueError, match="non-empty"):
        odometry.add_scan(np.zeros((0, 3)))


def test_surface_normals_of_the_scanned_room():
    """Ten lidar scans (σ 1.5 cm) of the room with its furniture,
    inserted with dynamic leaf depth; every node with a normal, up to 32 cm, against the
    nearest wall, floor, ceiling or box face (analytic): median < 5°."""
    from reference import nearest_face_normals

    rng = np.random.default_rng(12)
    boxes = earcore.synthetic.lidar_room(rng)
    m = earcore.SurfaceMap(0.01, position_memory=100)
    for k, pose in enumerate(earcore.synthetic.handheld_trajectory(rng, seconds=5.0)[::10]):
        scan = earcore.synthetic.render_lidar_scan(pose, [], boxes, seed=k)
        m.insert(scan @ pose[:3, :3].T + pose[:3, 3], pose[:3, 3], np.radians(2.0), max_leaf_size=0.16)
    positions, normals, depths = m.nodes()
    keep = ~np.isnan(normals[:, 0]) & (depths >= 11)
    cos = np.abs(np.sum(normals[keep] * nearest_face_normals(positions[keep], boxes), axis=1))
    errors = np.degrees(np.arccos(np.clip(cos, 0, 1)))
    assert keep.sum() > 500
    assert np.median(errors) < 5.0, np.median(errors)


def test_icp_against_walls_on_the_maps_central_planes_stays_where_it_starts():
    """A noise-free corner on x = 0, y = 0, z = 0 (the planes the root's children split
    on): points seen a little in front of a wall share no node below the root with it.
    Paired with the leaf beside them, they hold the alignment; left unpaired, only the
    points behind each wall pulled, all the same way, and ICP ran off (15 % of the points
    paired after 5 iterations, none after 50)."""
    rng = np.random.default_rng(0)
    corner = np.vstack([
        np.c_[np.zeros(900), rng.uniform(0, 1, (900, 2))],
        np.c_[rng.uniform(0, 1, 900), np.zeros(900), rng.uniform(0, 1, 900)],
        np.c_[rng.uniform(0, 1, (900, 2)), np.zeros(900)],
    ])
    surface = earcore.SurfaceMap(0.02)
    surface.insert(corner)
    surface.insert(corner)
    source = np.repeat(corner, 5, axis=0) + np.random.default_rng(2).normal(0, 0.003, (13_500, 3))
    for iterations in (5, 50):
        result = earcore.icp_point_to_plane(source, surface, max_iterations=iterations, sigma_tolerance=0.0)
        assert result.fitness > 0.9, (iterations, result.fitness)
        assert np.linalg.norm(result.transform[:3, 3]) < 0.005, result.transform[:3, 3]
