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


@pytest.mark.parametrize("distance", [0.0, 100.0, 3000.0, 100_000.0])
def test_an_alignment_far_from_the_origin_is_the_one_at_the_origin(scene, distance):
    """The same scene and offset moved `distance` from the coordinates' origin (a
    georeferenced or long odometry map): the same pose, converged and not degenerate.
    Rotating about the origin, the rotation's columns were nearly translations: a false
    degeneracy from 100 m, no convergence at 1 km, 1.6-1.9° off from 3 km."""
    pts, normals = scene
    far = np.array([distance, 0.5 * distance, 0.1 * distance])
    local = pose([0.3, -1, 0.5], 4.0, [0.03, -0.02, 0.04])  # target_from_source about the scene
    shift = np.eye(4)
    shift[:3, 3] = far
    truth = shift @ local @ np.linalg.inv(shift)
    source = (pts[::3] - local[:3, 3]) @ local[:3, :3] + far
    result = earcore.icp_point_to_plane(source, earcore.PlaneTarget(pts + far, normals), max_correspondence_distance=0.3)
    assert result.converged and not result.degenerate
    assert result.conditioning > 1e-3
    moved = source @ result.transform[:3, :3].T + result.transform[:3, 3]
    expected = source @ truth[:3, :3].T + truth[:3, 3]
    assert np.abs(moved - expected).max() < 2e-4 + 1e-14 * distance
    assert errors(result.transform, truth)[1] < 0.01


def test_a_fit_stopped_by_the_iteration_limit_reports_the_pose_it_returns(scene):
    """fitness and rmse describe the returned transform (brute-force pairs at it), not
    the pose the last step was found from."""
    from scipy.spatial import cKDTree

    pts, normals = scene
    truth = pose([0, 0, 1], 5.0, [0.05, -0.03, 0.02])
    source = (pts[::3] - truth[:3, 3]) @ truth[:3, :3]
    limit = 0.3
    for iterations in (1, 2):
        result = earcore.icp_point_to_plane(source, (pts, normals), max_iterations=iterations, max_correspondence_distance=limit)
        assert not result.converged
        moved = source @ result.transform[:3, :3].T + result.transform[:3, 3]
        distance, nearest = cKDTree(pts).query(moved)
        paired = distance <= limit
        residuals = np.einsum("ij,ij->i", moved[paired] - pts[nearest[paired]], normals[nearest[paired]])
        assert result.fitness == pytest.approx(paired.mean(), abs=1e-12)
        assert result.rmse == pytest.approx(np.sqrt(np.mean(residuals**2)), rel=1e-6)


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


def scipy_pairs(source, target_points, target_normals, transform, radius):
    """The source moved by `transform` and its nearest target points within `radius`
    with their unit normals, from scipy's k-d tree (independent of the core): the
    paired source points, target points and normals."""
    from scipy.spatial import cKDTree

    moved = source @ transform[:3, :3].T + transform[:3, 3]
    d, j = cKDTree(target_points).query(moved, distance_upper_bound=radius)
    keep = np.isfinite(d)
    n = target_normals[j[keep]]
    return moved[keep], target_points[j[keep]], n / np.linalg.norm(n, axis=1, keepdims=True)


def pose_covariance(source, target_points, target_normals, transform, radius):
    """σ²·H⁻¹ of the point-to-plane fit at `transform`, from the pairs recomputed with
    scipy (`scipy_pairs`): J = [p' × n, n], σ² the residuals' variance."""
    p, q, n = scipy_pairs(source, target_points, target_normals, transform, radius)
    r = np.einsum("ij,ij->i", p - q, n)
    jac = np.hstack([np.cross(p, n), n])
    sigma2 = r @ r / (len(r) - 6)
    return sigma2 * np.linalg.inv(jac.T @ jac)


@pytest.mark.parametrize("seed", range(3))
def test_the_default_stop_is_within_a_standard_deviation_of_the_converged_pose(scene, seed):
    """The default rule stops at the first step shorter than one standard deviation of
    the estimate: the result lies within a few of them of where ICP ends when run to
    the end, in fewer iterations. Noisy source, both the coarse-to-fine path (many
    points) and the plain one (few)."""
    pytest.importorskip("scipy")
    pts, normals = scene
    rng = np.random.default_rng(seed)
    truth = pose(rng.normal(size=3), rng.uniform(3, 8), rng.uniform(-0.06, 0.06, 3))
    for count in (3000, 12000):
        base = pts[rng.choice(len(pts), min(count, len(pts)), replace=False)]
        source = (base - truth[:3, 3]) @ truth[:3, :3] + rng.normal(0, 0.003, base.shape)
        target = earcore.PlaneTarget(pts, normals)
        default = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.3, max_iterations=200)
        full = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.3, max_iterations=200, sigma_tolerance=0.0)
        assert default.converged and default.iterations < full.iterations
        cov = pose_covariance(source, pts, normals, full.transform, 0.3)
        # The difference as a small-angle step (ω, t) applied on the left, in σ units.
        d = default.transform @ np.linalg.inv(full.transform)
        omega = np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]]) / 2
        step = np.concatenate([omega, d[:3, 3]])
        mahalanobis = float(np.sqrt(step @ np.linalg.solve(cov, step)))
        assert mahalanobis < 3.0, (count, mahalanobis)
        assert errors(default.transform, truth)[0] < 0.005


def huber_m_estimate(source, target_points, target_normals, transform, radius, width):
    """Huber's M-estimate for the pairs at `transform`, from scipy (k-d tree and
    least_squares, independent of the core): the small-angle step (ω, t) on the left from
    `transform` to it, and its covariance σ²·H⁻¹ (H over the pairs within the width,
    σ² = Σψ² / (those − 6), ψ the residual clipped to the width)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    p, q, n = scipy_pairs(source, target_points, target_normals, transform, radius)

    def residuals(x):
        return np.einsum("ij,ij->i", p @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:] - q, n)

    x = least_squares(residuals, np.zeros(6), loss="huber", f_scale=width, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    r = residuals(x)
    inliers = np.abs(r) <= width
    at = p @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:]
    jac = np.hstack([np.cross(at, n), n])[inliers]
    sigma2 = np.minimum(r * r, width * width).sum() / (inliers.sum() - 6)
    return x, sigma2 * np.linalg.inv(jac.T @ jac)


@pytest.mark.parametrize("seed", range(3))
def test_a_huber_kernel_ends_on_its_m_estimate(scene, seed):
    """Under Huber's kernel ICP takes Newton's steps on the kernel's loss, which end on
    the M-estimate for the final pairs, not just near it: within 1 % of a standard
    deviation of scipy's (the reweighted steps' linear convergence stopped 3-17 % away
    on these clouds). A third of the points are moved up to 4 cm."""
    pytest.importorskip("scipy")
    pts, normals = scene
    rng = np.random.default_rng(seed)
    truth = pose(rng.normal(size=3), 2.0, rng.normal(size=3) * 0.012)
    target = earcore.PlaneTarget(pts, normals)
    for count in (3000, 12000):
        base = pts[rng.choice(len(pts), count, replace=False)]
        source = (base - truth[:3, 3]) @ truth[:3, :3] + rng.normal(0, 0.002, base.shape)
        outliers = rng.choice(count, count * 3 // 10, replace=False)
        source[outliers] += rng.uniform(-0.04, 0.04, (len(outliers), 3))
        result = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.1, huber_delta=0.004)
        step, cov = huber_m_estimate(source, pts, normals, result.transform, 0.1, 0.004)
        assert result.converged
        assert float(np.sqrt(step @ np.linalg.solve(cov, step))) < 0.01, (count, step)
        assert errors(result.transform, truth)[0] < 0.001


@pytest.mark.parametrize("seed", [1, 6, 10])
def test_noisy_rooms_with_a_fixed_width_converge(seed):
    """Random rooms, one camera's view against four others', 8 mm noise, a fifth of the
    points moved up to 5 cm, a 2 cm kernel, 5 cm pairs: Newton's steps are taken only where
    they provably lower the kernel's loss, so the alignment converges as reweighted least
    squares does (6-9 iterations). Taking them up to 4× the inliers' curvature ran these
    seeds 50 iterations and left them 54-65 mm off."""
    rng = np.random.default_rng(seed)
    spheres, boxes = earcore.synthetic.random_scene(rng, n_shapes=10, extent=1.6)
    views = [
        earcore.synthetic.render_depth_points(
            earcore.synthetic.look_at([2.6 * np.cos(a), 2.6 * np.sin(a), 1.5], [0.0, 0.0, 0.4]), spheres, boxes, 0.0, max_depth=6.0
        )
        for a in 2 * np.pi * np.arange(5) / 5
    ]
    target = np.vstack(views[:4])
    target = target[rng.choice(len(target), 40000, replace=False)]
    true = views[4][rng.choice(len(views[4]), 6000, replace=False)]
    source = true + rng.normal(0, 0.008, true.shape)
    moved = rng.choice(len(source), len(source) // 5, replace=False)
    source[moved] += rng.uniform(-0.05, 0.05, (len(moved), 3))
    truth = pose(rng.normal(size=3), 2.0, [0.0, 0.0, 0.0])
    shift = rng.normal(size=3)
    truth[:3, 3] = 0.02 * shift / np.linalg.norm(shift)
    source = source @ truth[:3, :3].T + truth[:3, 3]
    target = earcore.PlaneTarget(target, earcore.estimate_normals(target, 20))
    result = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.05, huber_delta=0.02)
    assert result.converged and result.iterations <= 12, result
    assert errors(result.transform, np.linalg.inv(truth))[0] < 0.012


def test_step_tolerances_are_small_gicps_epsilons(scene):
    """translation_tolerance / rotation_tolerance stop at the first step below both (as
    small_gicp's and Open3D's epsilons): loose ones stop early and far, tight ones later
    and close; with every test off it runs to max_iterations."""
    pts, normals = scene
    truth = pose([0.3, -1, 0.5], 6.0, [0.04, 0.03, -0.05])
    source = (pts[::2] - truth[:3, 3]) @ truth[:3, :3]
    source = source + np.random.default_rng(4).normal(0, 0.004, source.shape)
    target = earcore.PlaneTarget(pts, normals)
    # Least squares: the default kernel starts only when a test passes, which `never` has not.
    off = dict(sigma_tolerance=0.0, max_correspondence_distance=0.3, huber_delta=None)
    loose = earcore.icp_point_to_plane(source, target, translation_tolerance=5e-3, rotation_tolerance=5e-3, **off)
    tight = earcore.icp_point_to_plane(source, target, translation_tolerance=1e-6, rotation_tolerance=1e-6, **off)
    never = earcore.icp_point_to_plane(source, target, max_iterations=60, **off)
    assert loose.converged and tight.converged and loose.iterations < tight.iterations
    assert not never.converged and never.iterations == 60
    # Tight ends where running on ends; loose stops short of it.
    assert errors(tight.transform, never.transform)[0] < 1e-5
    assert errors(loose.transform, never.transform)[0] > errors(tight.transform, never.transform)[0]


def corridor(rng, n):
    """Two walls and a floor along x, with door frames that fix x: an alignment along
    the corridor rests on a few percent of the points."""
    points, normals = [], []
    for y, ny in [(-1.0, 1.0), (1.0, -1.0)]:
        points.append(np.c_[rng.uniform(0, 10, n), np.full(n, y), rng.uniform(0, 2.5, n)])
        normals.append(np.tile([0.0, ny, 0.0], (n, 1)))
    points.append(np.c_[rng.uniform(0, 10, n), rng.uniform(-1, 1, n), np.zeros(n)])
    normals.append(np.tile([0.0, 0.0, 1.0], (n, 1)))
    for x0 in (2.0, 5.5, 8.0):
        for lo in (0.85, -1.0):
            m = n // 60
            points.append(np.c_[np.full(m, x0), rng.uniform(lo, lo + 0.15, m), rng.uniform(0, 2.5, m)])
            normals.append(np.tile([-1.0, 0.0, 0.0], (m, 1)))
    return np.vstack(points), np.vstack(normals)


@pytest.mark.parametrize("outliers", [0.0, 0.4])
def test_the_default_stop_weighs_residuals_as_the_kernel_does(outliers):
    """With a Huber kernel the step is weighted, so the residual variance it is measured
    against must be too: 15 cm along a corridor, clean or with 40 % outliers, ends
    within millimetres instead of stopping after the first step."""
    target = earcore.PlaneTarget(*corridor(np.random.default_rng(1), 30000))
    source = corridor(np.random.default_rng(7), 1500)[0] - [0.15, 0.0, 0.0]
    source = source + np.random.default_rng(2).normal(0, 0.003, source.shape)
    moved = np.random.default_rng(3).choice(len(source), int(len(source) * outliers), replace=False)
    source[moved] += np.random.default_rng(4).normal(0, 0.2, (len(moved), 3))
    result = earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.5, max_iterations=500, huber_delta=0.01)
    assert result.converged and abs(result.transform[0, 3] - 0.15) < 0.003, result


def test_a_coarse_stage_with_few_pairs_does_not_decide(scene):
    """A large source whose few points near the target are noisy and the rest never
    pair: one point more (over the coarse stage's threshold) must not turn a working
    alignment into an error or a worse pose."""
    pts, normals = scene
    target = earcore.PlaneTarget(pts, normals)
    rng = np.random.default_rng(296)
    truth = pose(rng.normal(size=3), 6.0, [0.05, -0.03, 0.04])
    near = pts[rng.choice(len(pts), 30, replace=False)]
    near = (near - truth[:3, 3]) @ truth[:3, :3] + rng.normal(0, 0.005, near.shape)
    far = rng.uniform(-1, 1, (9000, 3)) + 30  # never paired
    results = []
    for n in (8191, 8192):
        source = np.vstack([near, far[: n - len(near)]])
        results.append(earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.3, max_iterations=30))
    assert errors(results[1].transform, truth)[0] <= errors(results[0].transform, truth)[0] + 1e-3


def test_one_step_tolerance_alone_is_used():
    """`translation_tolerance` given alone stops on the translation (the rotation's 0
    leaves the rule, not blocks it)."""
    target = earcore.PlaneTarget(*corridor(np.random.default_rng(1), 20000))
    source = corridor(np.random.default_rng(7), 1500)[0] + [0.05, 0.02, 0.0]
    alone = earcore.icp_point_to_plane(source, target, sigma_tolerance=0.0, translation_tolerance=1e-3, max_iterations=200)
    assert alone.converged and alone.iterations < 200


def test_the_default_kernel_stops_an_unseen_surface_pulling(scene):
    """The default kernel ("auto"): the source sees a board 3 cm in front of a wall
    that the target saw bare (600 points, a tenth of the source). Least squares (None)
    pairs the board with the wall and ends 7 mm off the true pose; the default ends
    within a millimetre, as does a fixed Huber width near the noise."""
    pts, normals = scene
    target = earcore.PlaneTarget(pts, normals)
    rng = np.random.default_rng(11)
    truth = pose([0.2, 1.0, 0.4], 3.0, [0.03, -0.02, 0.02])
    seen = pts[rng.choice(len(pts), 6000, replace=False)] + rng.normal(0, 0.001, (6000, 3))
    board = np.column_stack([np.full(600, -1.47), rng.uniform(-1.0, 1.0, 600), rng.uniform(0.8, 2.0, 600)])
    world = np.vstack([seen, board])
    source = (world - truth[:3, 3]) @ truth[:3, :3]  # truth maps the source onto the world
    found = {
        kernel: errors(earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.2, huber_delta=kernel).transform, truth)[0]
        for kernel in ("auto", None, 0.002)
    }
    assert found[None] > 0.005, found
    assert found["auto"] < 0.2 * found[None] and found["auto"] < 0.001, found
    assert found[0.002] < 0.0012, found
    assert earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.2).transform.tolist() == (
        earcore.icp_point_to_plane(source, target, max_correspondence_distance=0.2, huber_delta="auto").transform.tolist()
    )


def test_the_kernel_argument_is_checked(scene):
    pts, normals = scene
    target = earcore.PlaneTarget(pts, normals)
    with pytest.raises(ValueError, match="huber_delta must be"):
        earcore.icp_point_to_plane(pts[:500], target, huber_delta="huber")
    with pytest.raises(ValueError, match="not both"):
        earcore._earcore.icp_point_to_plane_raw(pts[:500], target, huber_delta=0.01, adaptive_huber=True)
