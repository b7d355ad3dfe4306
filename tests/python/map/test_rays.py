"""Analytic geometry: a sphere scanned from its centre, rays cast back at it."""

from __future__ import annotations

import numpy as np
import pytest

import earcore


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


@pytest.mark.parametrize("resolution, radius", [(0.05, 1.0), (0.02, 0.6)])
def test_rays_from_the_centre_hit_the_sphere_at_its_radius(resolution, radius):
    centre = np.array([0.31, -0.22, 1.07])
    tree = earcore.OcTree(resolution)
    tree.insert_point_cloud(centre + radius * fibonacci_sphere(200_000), centre)
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(5000, 3))
    hits, ends = tree.cast_rays(centre, directions)
    assert hits.all(), "the shell is closed: every ray must hit it"
    distances = np.linalg.norm(ends - centre, axis=1)
    # The end is a cell centre: within one voxel diagonal of the true surface point.
    assert np.all(np.abs(distances - radius) <= resolution * np.sqrt(3))
    # Inside is free, outside unknown, the shell occupied.
    assert (tree.is_occupied(centre + 0.5 * radius * fibonacci_sphere(1000)) == 0).all()
    assert (tree.is_occupied(centre + 1.5 * radius * fibonacci_sphere(1000)) == -1).all()
    assert (tree.is_occupied(centre + radius * fibonacci_sphere(1000)) == 1).mean() > 0.95


def test_cast_ray_stops_at_unknown_and_max_range():
    tree = earcore.OcTree(0.1)
    tree.insert_point_cloud([[2.05, 0.05, 0.05]], [0.05, 0.05, 0.05])
    hit, end = tree.cast_ray([0.05, 0.05, 0.05], [1, 0, 0])
    assert hit and np.allclose(end, [2.05, 0.05, 0.05])
    hit, end = tree.cast_ray([0.05, 0.05, 0.05], [1, 0, 0], max_range=1.0)
    # OctoMap stops at the first cell whose centre is beyond max_range and returns it.
    assert not hit and np.allclose(end, [1.15, 0.05, 0.05])
    hit, end = tree.cast_ray([0.05, 0.05, 0.05], [0, 1, 0])
    assert not hit, "unknown space stops the ray unless ignore_unknown"
    hit, _ = tree.cast_ray([0.05, 0.05, 0.05], [0, 1, 0], max_range=2.0, ignore_unknown=True)
    assert not hit
    # From beyond the wall, through cells no ray has seen: unknown space stops the ray
    # unless it is ignored, and then the wall is hit (pyoctomap's castRay agrees).
    hit, end = tree.cast_ray([3.05, 0.05, 0.05], [-1, 0, 0])
    assert not hit and np.allclose(end, [3.05, 0.05, 0.05])
    hit, end = tree.cast_ray([3.05, 0.05, 0.05], [-1, 0, 0], ignore_unknown=True)
    assert hit and np.allclose(end, [2.05, 0.05, 0.05])
    hit, _ = tree.cast_ray([3.05, 0.05, 0.05], [-1, 0, 0], max_range=0.5, ignore_unknown=True)
    assert not hit


def test_leaves_in_a_box_and_occupied_voxels():
    tree = earcore.OcTree(0.1)
    tree.insert_point_cloud([[2.05, 0.05, 0.05], [0.05, 2.05, 0.05]], [0.05, 0.05, 0.05])
    centres, sizes = tree.occupied_voxels()
    np.testing.assert_allclose(centres[np.argsort(centres[:, 0])], [[0.05, 2.05, 0.05], [2.05, 0.05, 0.05]], atol=1e-9)
    assert np.all(sizes == 0.1)
    c, s, l = tree.leaves([1.0, -0.1, -0.1], [3.0, 0.1, 0.1])
    assert len(c) and np.all(c[:, 0] + s / 2 >= 1.0) and np.all(c[:, 0] - s / 2 <= 3.0)
    all_c, _, _ = tree.leaves()
    assert len(all_c) == tree.num_leaf_nodes() > len(c)
    assert tree.memory_usage() > 0 and len(tree) == tree.size()
