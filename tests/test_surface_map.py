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
