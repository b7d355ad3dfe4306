"""Pre-processing against brute-force references written here (numpy, O(N²) where needed)."""

from __future__ import annotations

import numpy as np
import pytest

import earcore

K = dict(fx=365.0, fy=366.5, cx=255.5, cy=211.5)


def brute_force_outliers(points: np.ndarray, k: int, std_ratio: float) -> np.ndarray:
    """PCL's rule, computed from the full distance matrix."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    np.fill_diagonal(d, np.inf)  # a point is not its own neighbour
    mean_knn = np.sort(d, axis=1)[:, :k].mean(axis=1)
    threshold = mean_knn.mean() + std_ratio * mean_knn.std(ddof=1)
    return np.flatnonzero(mean_knn <= threshold)


def test_back_projection_of_a_fronto_parallel_plane_is_exact():
    depth = np.full((424, 512), 1.25, dtype=np.float32)
    depth[10, 20] = 0.0  # no reading
    depth[11, 21] = np.nan
    depth[12, 22] = 9.0  # beyond max_depth
    pts, pixels = earcore.depth_to_points(depth, **K, max_depth=4.5, return_pixels=True)
    assert len(pts) == depth.size - 3
    v, u = np.divmod(pixels.astype(np.int64), 512)
    np.testing.assert_allclose(pts[:, 2], 1.25)
    np.testing.assert_allclose(pts[:, 0], (u - K["cx"]) / K["fx"] * 1.25, atol=1e-12)
    np.testing.assert_allclose(pts[:, 1], (v - K["cy"]) / K["fy"] * 1.25, atol=1e-12)


def test_tilted_plane_points_lie_on_the_plane():
    n, c = np.array([0.3, -0.2, 1.0]), 2.0  # plane n·p = c in the camera frame
    v, u = np.mgrid[0:424, 0:512]
    rays = np.stack([(u - K["cx"]) / K["fx"], (v - K["cy"]) / K["fy"], np.ones_like(u, dtype=float)], axis=-1)
    depth = (c / (rays @ n)).astype(np.float32)
    pts = earcore.depth_to_points(depth, **K)
    np.testing.assert_allclose(pts @ n, c, rtol=1e-6)


def test_distortion_round_trips_through_the_forward_model():
    k1, k2, p1, p2, k3 = -0.28, 0.09, 0.0012, -0.0007, -0.01
    depth = np.full((120, 160), 0.8, dtype=np.float32)
    k = dict(fx=120.0, fy=121.0, cx=79.5, cy=59.5)
    pts, pixels = earcore.depth_to_points(depth, **k, distortion=[k1, k2, p1, p2, k3], return_pixels=True)
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    v, u = np.divmod(pixels.astype(np.int64), 160)
    np.testing.assert_allclose(xd * k["fx"] + k["cx"], u, atol=1e-6)
    np.testing.assert_allclose(yd * k["fy"] + k["cy"], v, atol=1e-6)


def test_pose_colour_and_millimetre_depth():
    depth_mm = np.full((4, 5), 1000, dtype=np.uint16)
    colour = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    pose = earcore.synthetic.look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    pts, rgb = earcore.depth_to_points(depth_mm, 2.0, 2.0, 2.0, 1.5, depth_scale=0.001, base_from_camera=pose, colour=colour)
    cam = earcore.depth_to_points(depth_mm.astype(float) / 1000, 2.0, 2.0, 2.0, 1.5)
    np.testing.assert_allclose(pts, cam @ pose[:3, :3].T + pose[:3, 3], atol=1e-12)
    np.testing.assert_array_equal(rgb, colour.reshape(-1, 3))
    assert rgb.dtype == np.uint8


@pytest.mark.parametrize(
    "kwargs, error",
    [
        (dict(fx=0.0), ValueError),
        (dict(fy=-1.0), ValueError),
        (dict(cx=float("nan")), ValueError),
        (dict(distortion=[0.1, 0.2, 0.3]), ValueError),
        (dict(base_from_camera=np.diag([1.0, 1.0, -1.0, 1.0])), ValueError),
        (dict(base_from_camera=np.eye(3)), ValueError),
        (dict(depth_scale=0.0), ValueError),
        (dict(min_depth=2.0, max_depth=1.0), ValueError),
    ],
)
def test_depth_to_points_rejects_bad_input(kwargs, error):
    args = {**K, **kwargs}
    with pytest.raises(error):
        earcore.depth_to_points(np.ones((4, 4), np.float32), **args)
    with pytest.raises(ValueError):
        earcore.depth_to_points(np.ones(16, np.float32), **K)


def test_crop_sphere_and_box_match_numpy():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (20_000, 3))
    kept, idx = earcore.crop(pts, return_index=True)
    np.testing.assert_array_equal(idx, np.flatnonzero(np.linalg.norm(pts, axis=1) <= 1.5))
    np.testing.assert_array_equal(kept, pts[idx])
    centre = [0.5, -0.2, 1.0]
    idx = earcore.crop(pts, center=centre, radius=0.7, return_index=True)[1]
    np.testing.assert_array_equal(idx, np.flatnonzero(np.sum((pts - centre) ** 2, axis=1) <= 0.49))
    lo, hi = np.array([-1.0, 0.0, -0.5]), np.array([2.0, 1.0, 0.5])
    idx = earcore.crop(pts, box_min=lo, box_max=hi, return_index=True)[1]
    np.testing.assert_array_equal(idx, np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1)))
    with pytest.raises(ValueError):
        earcore.crop(pts, box_min=hi, box_max=lo)
    with pytest.raises(ValueError):
        earcore.crop(pts, box_min=lo)


@pytest.mark.parametrize("k, std_ratio", [(20, 2.0), (8, 1.0), (30, 0.5)])
def test_statistical_outlier_removal_equals_brute_force(k, std_ratio):
    rng = np.random.default_rng(k)
    surface = rng.uniform(-1, 1, (1500, 3)) * [1, 1, 0.01]
    noise = rng.uniform(-2, 2, (60, 3))
    pts = np.vstack([surface, noise, surface[:40]])  # duplicates too
    kept, idx = earcore.remove_statistical_outliers(pts, k, std_ratio, return_index=True)
    np.testing.assert_array_equal(idx, brute_force_outliers(pts, k, std_ratio))
    assert (idx < 1500).mean() > 0.9


def test_statistical_outlier_removal_equals_brute_force_on_uneven_density():
    # Blobs of very different spreads: neighbouring points' k-th distances differ by
    # orders of magnitude, so the per-point distance guess must widen (and the grid
    # fall back to the k-d tree) without changing the answer.
    rng = np.random.default_rng(7)
    blobs = [rng.normal(rng.uniform(-2, 2, 3), scale, (n, 3)) for scale, n in [(0.002, 400), (0.05, 800), (0.4, 900)]]
    pts = rng.permutation(np.vstack(blobs + [rng.uniform(-3, 3, (100, 3))]))
    for k in (5, 20):
        _, idx = earcore.remove_statistical_outliers(pts, k, 1.0, return_index=True)
        np.testing.assert_array_equal(idx, brute_force_outliers(pts, k, 1.0))


@pytest.mark.parametrize("k", [1, 5, 20])
def test_statistical_outlier_removal_with_many_duplicates(k):
    # A point with k copies of itself has a k-th distance of 0; the next point must not
    # start (and get stuck) at a zero distance guess.
    rng = np.random.default_rng(k)
    surface = rng.uniform(-1, 1, (600, 3)) * [1, 1, 0.01]
    pts = np.vstack([np.repeat(surface[:30], k + 2, axis=0), surface, rng.uniform(-2, 2, (20, 3))])
    _, idx = earcore.remove_statistical_outliers(pts, k, 1.0, return_index=True)
    np.testing.assert_array_equal(idx, brute_force_outliers(pts, k, 1.0))


def test_statistical_outlier_removal_rejects_bad_input():
    with pytest.raises(ValueError, match="more points"):
        earcore.remove_statistical_outliers(np.zeros((5, 3)), k=5)
    with pytest.raises(ValueError, match="not finite"):
        earcore.remove_statistical_outliers(np.full((50, 3), np.nan), k=5)
    with pytest.raises(ValueError):
        earcore.remove_statistical_outliers(np.zeros((50, 3)), k=0)


@pytest.mark.parametrize("layout", ["random", "runs", "far apart"])
def test_voxel_grid_centroids_are_exact(layout):
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 0.5, (30_000, 3))
    if layout == "runs":  # neighbours share voxels, as along a depth image's rows
        pts = pts[np.lexsort(np.floor(pts / 0.05).T)]
    elif layout == "far apart":  # beyond what a packed 21-bit-per-axis key can span
        pts[::2] += 1.0e6
    colours = rng.integers(0, 255, (30_000, 3)).astype(np.float64)
    centroids, mean_colours = earcore.voxel_downsample(pts, 0.05, colours)
    keys = np.floor(pts / 0.05).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    counts = np.bincount(inverse)
    ref = np.stack([np.bincount(inverse, weights=pts[:, a]) for a in range(3)], axis=1) / counts[:, None]
    ref_colours = np.stack([np.bincount(inverse, weights=colours[:, a]) for a in range(3)], axis=1) / counts[:, None]
    order = np.argsort(first)  # earcore lists voxels in order of their first point
    np.testing.assert_allclose(centroids, ref[order], rtol=0, atol=1e-12)
    np.testing.assert_allclose(mean_colours, ref_colours[order], rtol=0, atol=1e-9)
    assert np.array_equal(earcore.voxel_downsample(pts, 0.05), centroids)
    single = earcore.voxel_downsample(pts, 0.05, colours[:, 0])[1]
    assert single.shape == (len(centroids),)
    with pytest.raises(ValueError):
        earcore.voxel_downsample(pts, 0.0)
    with pytest.raises(ValueError):
        earcore.voxel_downsample(pts, 0.05, colours[:10])


def test_voxel_means_are_the_means_of_the_points_in_each_voxel():
    rng = np.random.default_rng(5)
    res = 0.05
    pts = rng.normal(0, 0.3, (20_000, 3))
    cells = np.unique(np.floor(pts / res), axis=0)
    # Some voxels with points, some without (those keep their centre), in any order.
    wanted = np.vstack([cells[rng.choice(len(cells), 300, replace=False)], np.floor(rng.uniform(5, 6, (50, 3)) / res)])
    wanted = wanted[rng.permutation(len(wanted))]
    centres = (wanted + 0.5) * res
    means = earcore.cloud.voxel_means(centres, pts, res)
    cell_of = np.floor(pts / res)
    for centre, cell, mean in zip(centres, wanted, means):
        inside = pts[np.all(cell_of == cell, axis=1)]
        expected = inside.mean(axis=0) if len(inside) else centre
        np.testing.assert_allclose(mean, expected, rtol=0, atol=1e-12)
    assert np.array_equal(earcore.cloud.voxel_means(centres, np.zeros((0, 3)), res), centres)
    assert earcore.cloud.voxel_means(np.zeros((0, 3)), pts, res).shape == (0, 3)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.abs(np.sum(a * b, axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_normals_of_a_noisy_plane_and_a_sphere():
    rng = np.random.default_rng(5)
    n = np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, -1.0])  # plane z = 0.3x + 0.1y + 1
    xy = rng.uniform(-1, 1, (5000, 2))
    plane = np.column_stack([xy, 0.3 * xy[:, 0] + 0.1 * xy[:, 1] + 1.0 + rng.normal(0, 0.001, 5000)])
    normals, variation = earcore.estimate_normals(plane, 20, viewpoint=[0, 0, 5], return_variation=True)
    assert np.median(angle_deg(normals, np.tile(n, (5000, 1)))) < 1.0
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.all(normals @ [0, 0, 1] > 0), "normals face the viewpoint above the plane"
    assert np.median(variation) < 0.01
    sphere = rng.normal(size=(8000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    normals = earcore.estimate_normals(sphere, 15)  # viewpoint at the centre: normals point inwards
    assert np.median(angle_deg(normals, sphere)) < 2.0
    assert np.all(np.sum(normals * sphere, axis=1) < 0)


def test_normals_reject_bad_input():
    with pytest.raises(ValueError):
        earcore.estimate_normals(np.zeros((10, 3)), k=20)
    with pytest.raises(ValueError):
        earcore.estimate_normals(np.zeros((50, 3)), k=1)
    with pytest.raises(ValueError):
        earcore.estimate_normals(np.full((50, 3), np.inf), k=5)


def test_normals_of_boxes_seen_by_a_depth_camera():
    """A Kinect V2 (512 × 424, the simulated sensor's axial noise
    model, ~2 mm at 2.5 m) sees a table-sized box, a cube and the floor; PCA normals of
    the 1 cm voxel grid against each point's nearest box face (analytic): median < 5°."""
    from earcore.sim.sensors import SENSORS
    from reference import nearest_face_normals

    boxes = np.array([[-0.6, -0.4, 0.0, 0.6, 0.4, 0.75], [0.8, 0.3, 0.0, 1.1, 0.6, 0.3], [-3, -3, -0.2, 3, 3, 0.0]])
    camera = earcore.synthetic.look_at([2.0, -1.6, 1.7], [0.0, 0.0, 0.4])
    points = earcore.synthetic.render_depth_points(camera, [], boxes)
    rng = np.random.default_rng(6)
    ray = points - camera[:3, 3]
    depth = np.linalg.norm(ray, axis=1, keepdims=True)
    sigma = SENSORS["kinect_v2"].sigma(depth)
    noisy = points + ray / depth * rng.normal(size=(len(points), 1)) * sigma
    grid = earcore.voxel_downsample(noisy, 0.01)
    normals = earcore.estimate_normals(grid, 20, viewpoint=camera[:3, 3])
    errors = angle_deg(normals, nearest_face_normals(grid, boxes))
    assert len(grid) > 5000
    assert np.median(errors) < 5.0, np.median(errors)
