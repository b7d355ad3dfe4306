"""Point-to-plane ICP on synthetic scenes with known offsets."""

from __future__ import annotations

import numpy as np
import pytest

import earcore


def rotation(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def pose(axis, angle_deg, t):
    m = np.eye(4)
    m[:3, :3] = rotation(axis, angle_deg)
    m[:3, 3] = t
    return m


def errors(estimate, truth):
    d = np.linalg.inv(truth) @ estimate
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return np.linalg.norm(d[:3, 3]), angle


@pytest.fixture(scope="module")
def scene():
    """A room corner with a table and a sphere, seen by one depth camera: points and
    exact-enough normals (PCA of the dense cloud)."""
    cam = earcore.synthetic.look_at([2.2, -1.9, 1.6], [0.0, 0.0, 0.5])
    spheres = [[0.2, 0.1, 1.0, 0.3]]
    boxes = [[-0.6, -0.4, 0.0, 0.6, 0.4, 0.75], [-1.6, -2.5, 0.0, -1.5, 2.5, 2.5], [-2.5, 1.5, 0.0, 2.5, 1.6, 2.5]]
    pts = earcore.synthetic.render_depth_points(cam, spheres, boxes, 0.0, width=320, height=240, fx=230, fy=230, cx=159.5, cy=119.5)
    normals = earcore.estimate_normals(pts, 15, viewpoint=cam[:3, 3])
    return pts, normals


@pytest.mark.parametrize(
    "axis, angle, t",
    [([0, 0, 1], 10.0, [0.1, -0.1, 0.05]), ([1, 1, 0], -8.0, [-0.1, 0.08, 0.1]), ([0.3, -1, 0.5], 10.0, [0.0, 0.1, -0.1])],
)
def test_recovers_large_offsets_exactly_without_noise(scene, axis, angle, t):
    pts, normals = scene
    target = earcore.PlaneTarget(pts, normals)
    truth = pose(axis, angle, t)  # target_from_source
    source = (pts[::3] - truth[:3, 3]) @ truth[:3, :3]  # = inverse(truth) applied to target points
    result = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.5, max_iterations=100)
    dt, dr = errors(result.transform, truth)
    assert result.converged and not result.degenerate
    assert dt <= 1e-3 and dr <= 0.05, (dt, dr)
    assert result.fitness > 0.95 and result.rmse < 1e-3


def test_noise_and_outliers_stay_within_the_noise(scene):
    pts, normals = scene
    rng = np.random.default_rng(0)
    truth = pose([0.2, 1, -0.4], 6.0, [0.05, -0.07, 0.04])
    source = (pts[::3] - truth[:3, 3]) @ truth[:3, :3]
    source = source + rng.normal(0, 0.01, source.shape)
    outliers = rng.uniform(source.min(0), source.max(0), (len(source) // 10, 3))
    source = np.vstack([source, outliers])
    result = earcore.icp_point_to_plane(source, (pts, normals), max_correspondence_distance=0.3, huber_delta=0.02)
    dt, dr = errors(result.transform, truth)
    assert dt <= 0.01 and dr <= 0.5, (dt, dr)


def test_a_single_plane_is_degenerate():
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)])
    normals = np.tile([0.0, 0.0, 1.0], (3000, 1))
    with pytest.warns(earcore.DegenerateAlignmentWarning):
        result = earcore.icp_point_to_plane(plane[::2] + [0.05, 0.02, 0.01], (plane, normals))
    assert result.degenerate
    assert abs(result.transform[2, 3] + 0.01) < 1e-6, "the constrained direction is still solved"


def test_icp_rejects_bad_input(scene):
    pts, normals = scene
    target = earcore.PlaneTarget(pts, normals)
    with pytest.raises(ValueError, match="at least 6"):
        earcore.icp_point_to_plane(pts[:3], target)
    with pytest.raises(ValueError, match="not finite"):
        earcore.icp_point_to_plane(np.full((50, 3), np.nan), target)
    skewed = np.eye(4)
    skewed[0, 1] = 0.3
    with pytest.raises(ValueError, match="rigid"):
        earcore.icp_point_to_plane(pts[:100], target, skewed)
    with pytest.raises(ValueError, match="within"):
        earcore.icp_point_to_plane(pts[:100] + 100.0, target)
    with pytest.raises(ValueError):
        earcore.PlaneTarget(pts, normals[:10])
    with pytest.raises(ValueError):
        earcore.PlaneTarget(pts[:10], np.zeros((10, 3)))
    with pytest.raises(TypeError):
        earcore.icp_point_to_plane(pts, pts)


def test_alignment_against_a_surface_map(scene):
    """NOctoSLAM's setting: register a scan against the surface map of earlier scans."""
    pts, _ = scene
    surface = earcore.SurfaceMap(0.02)
    surface.insert(pts)
    truth = pose([0.1, 0.3, 1.0], 2.0, [0.02, -0.015, 0.01])
    source = (pts[1::4] - truth[:3, 3]) @ truth[:3, :3]
    start_dt, start_dr = errors(np.eye(4), truth)
    result = earcore.icp_point_to_plane(source, surface, max_correspondence_distance=0.1)
    dt, dr = errors(result.transform, truth)
    # Points whose branch has no normal yet (edges, sparse spots) get no pair.
    assert result.fitness > 0.6
    assert dt < 0.25 * start_dt and dr < 0.25 * start_dr, (dt, dr, start_dt, start_dr)
    assert dt < 0.01 and dr < 0.5


def test_multi_camera_fine_alignment():
    """Three cameras around a cell, poses off by up to 3 cm / 3° (the reference camera
    excepted), refined against each other to a few millimetres / tenths of a degree."""
    spheres = [[0.2, 0.1, 1.0, 0.3], [-0.4, -0.5, 0.9, 0.15]]
    boxes = [[-0.6, -0.4, 0.0, 0.6, 0.4, 0.75], [-1.6, -2.5, 0.0, -1.5, 2.5, 2.5], [-2.5, 1.5, 0.0, 2.5, 1.6, 2.5]]
    camera = dict(width=320, height=240, fx=230, fy=230, cx=159.5, cy=119.5, max_depth=4.5)
    truths = [
        earcore.synthetic.look_at([2.2, -1.9, 1.6], [0.0, 0.0, 0.5]),
        earcore.synthetic.look_at([2.4, 1.2, 1.8], [0.0, 0.0, 0.4]),
        earcore.synthetic.look_at([0.3, -2.3, 2.2], [-0.3, 0.3, 0.3]),
    ]
    clouds = []
    for t in truths:
        world = earcore.synthetic.render_depth_points(t, spheres, boxes, 0.0, **camera)
        clouds.append((world - t[:3, 3]) @ t[:3, :3])  # into the camera frame
    rng = np.random.default_rng(3)
    guesses = [truths[0]]
    for t in truths[1:]:
        axis = rng.normal(size=3)
        guesses.append(t @ pose(axis, 3.0, rng.uniform(-1, 1, 3) / np.sqrt(3) * 0.03))
    refined = earcore.refine_camera_poses(clouds, guesses)
    np.testing.assert_array_equal(refined[0], truths[0])
    for est, truth, guess in zip(refined[1:], truths[1:], guesses[1:]):
        start = errors(guess, truth)
        dt, dr = errors(est, truth)
        assert start[1] > 2.9
        assert dt <= 0.003 and dr <= 0.2, (dt, dr, start)
