"""Inputs that could give a wrong answer without a word give the right answer or a
clear error; each answer is checked against an independent
reference (the sensor model's log-odds, a scaled scene, analytic geometry, the file
as OctoMap writes it)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import earcore
from earcore import urdf

# ---- update_node: numpy bools are hits and misses -------------------------------------


def _log_odds(p: float) -> np.float32:
    return np.float32(math.log(p / (1 - p)))


@pytest.mark.parametrize(
    "update, expected",
    [
        (True, _log_odds(0.7)),
        (False, _log_odds(0.4)),
        (np.True_, _log_odds(0.7)),
        (np.False_, _log_odds(0.4)),
        (np.bool_(1), _log_odds(0.7)),
        (np.array(False), _log_odds(0.4)),
        (0.0, np.float32(0.0)),
        (1.0, np.float32(1.0)),
        (np.float32(-0.25), np.float32(-0.25)),
        (np.int64(2), np.float32(2.0)),
    ],
    ids=repr,
)
def test_update_node_reads_bools_as_hit_or_miss_and_numbers_as_log_odds(update, expected):
    tree = earcore.OcTree(0.1, prob_hit=0.7, prob_miss=0.4)
    tree.update_node([0.05, 0.05, 0.05], update)
    assert tree.log_odds([[0.05, 0.05, 0.05]])[0] == pytest.approx(expected, abs=1e-6)
    # A miss leaves the cell free, a hit occupied: the bug made np.False_ occupied.
    if isinstance(update, (bool, np.bool_)) or getattr(update, "dtype", None) == np.bool_:
        assert tree.is_occupied([[0.05, 0.05, 0.05]])[0] == int(bool(update))


@pytest.mark.parametrize(
    "update", [1 + 0j, np.complex128(0.5), np.array([True]), np.array([0.5, 0.5]), "hit", None, np.datetime64(1, "s")],
    ids=repr,
)
def test_update_node_refuses_what_is_neither(update):
    tree = earcore.OcTree(0.1)
    tree.update_node([0, 0, 0], True)
    with pytest.raises(TypeError, match="update must be a bool"):
        tree.update_node([0, 0, 0], update)
    assert tree.log_odds([[0, 0, 0]])[0] == pytest.approx(_log_odds(0.7))


# ---- resolutions the key arithmetic can represent -------------------------------------

#: The documented range (README, "Bad input"): one cell's squared length must be a
#: normal float32, the map's squared diagonal a finite one.
MIN_RESOLUTION, MAX_RESOLUTION = 1e-18, 1e14


def _scene_in_cells(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    far = rng.uniform(-32000, 32000, (20, 3))
    near = rng.uniform(-4, 4, (300, 3))
    return np.vstack([far, near]), np.array([0.3, -0.6, 0.45])


def _leaves_at(resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cells, origin = _scene_in_cells()
    tree = earcore.OcTree(resolution)
    tree.insert_point_cloud(cells * resolution, origin * resolution)
    return tree.leaf_keys()


@pytest.mark.parametrize("exponent", [-59, -40, 20, 46])
def test_scenes_are_identical_across_the_resolution_range(exponent):
    """Scaling by a power of two is exact in float and double, so a scene given in
    cells must produce the same keys and log-odds at every accepted resolution as at
    1 m (the bug: free cells vanished at tiny resolutions, rays ran off at huge ones)."""
    resolution = 2.0**exponent
    assert MIN_RESOLUTION <= resolution <= MAX_RESOLUTION
    reference = _leaves_at(1.0)
    got = _leaves_at(resolution)
    for a, b in zip(reference, got):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("resolution", [1e-100, 1e-20, 9.9e-19, 1.01e14, 1e20, 1e308])
def test_resolutions_outside_the_range_are_refused(resolution, tmp_path):
    with pytest.raises(ValueError, match=r"resolution .*\[1e-18, 1e14\]"):
        earcore.OcTree(resolution)
    with pytest.raises(ValueError, match=r"resolution .*\[1e-18, 1e14\]"):
        earcore.SurfaceMap(resolution)
    # A file claiming such a resolution is a corrupt file.
    good = tmp_path / "good.ot"
    earcore.OcTree(0.1).write(good)
    bad = tmp_path / "bad.ot"
    bad.write_bytes(good.read_bytes().replace(b"res 0.1\n", f"res {resolution!r}\n".encode()))
    with pytest.raises(earcore.MapFormatError, match="resolution"):
        earcore.OcTree.read(bad)


def test_the_range_bounds_themselves_are_accepted():
    for resolution in (MIN_RESOLUTION, MAX_RESOLUTION):
        assert earcore.OcTree(resolution).resolution == resolution
        assert earcore.SurfaceMap(resolution).resolution == resolution


def test_point_magnitudes_beyond_float32_are_off_the_map():
    """Points are float32 as in OctoMap: 1e39 would become inf, a key of nothing."""
    tree = earcore.OcTree(MAX_RESOLUTION)
    for p in ([1e39, 0, 0], [0, -1e300, 0]):
        with pytest.raises(earcore.OutOfMapError):
            tree.insert_point_cloud([p], [0, 0, 0])
        with pytest.raises(earcore.OutOfMapError):
            tree.update_node(p, True)
    assert tree.size() == 0


def test_a_max_range_beyond_every_ray_is_no_limit():
    cells, origin = _scene_in_cells()
    points = cells * 0.05
    plain, huge = earcore.OcTree(0.05), earcore.OcTree(0.05)
    plain.insert_point_cloud(points, origin * 0.05)
    huge.insert_point_cloud(points, origin * 0.05, max_range=1e308)
    for a, b in zip(plain.leaf_keys(), huge.leaf_keys()):
        np.testing.assert_array_equal(a, b)
    hit_a = plain.cast_ray([0, 0, 0], [1, 0.2, 0.1])
    hit_b = plain.cast_ray([0, 0, 0], [1, 0.2, 0.1], max_range=1e308)
    assert hit_a[0] == hit_b[0] and np.array_equal(hit_a[1], hit_b[1])


# ---- fitting a body to points on a segment --------------------------------------------


@pytest.mark.parametrize(
    "direction",
    [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, -1), (1, 1, 1), (0.6, 0, 0.8), (-0.3, 0.4, 0.5)],
    ids=str,
)
@pytest.mark.parametrize("shape", ["cylinder", "capsule", "auto"])
def test_points_on_a_segment_fit_the_segment(direction, shape):
    """Analytic answer: radius 0 (plus padding) around the segment itself; the bug gave
    a disc of radius L/2 across it for every axis but x."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    start, length = np.array([0.1, -0.2, 0.3]), 0.7
    points = start + np.linspace(0, length, 21)[:, None] * d
    a, b, radius, got_shape = earcore.fit_body(points, 0.0, shape)
    a, b = np.asarray(a), np.asarray(b)
    assert radius < 1e-9
    if np.linalg.norm(a - start) > np.linalg.norm(b - start):
        a, b = b, a
    np.testing.assert_allclose(a, start, atol=1e-9)
    np.testing.assert_allclose(b, start + length * d, atol=1e-9)
    assert got_shape in ("cylinder", "capsule")


# ---- map files hold one tree and end with it ------------------------------------------


@pytest.fixture
def small_tree():
    tree = earcore.OcTree(0.1)
    rng = np.random.default_rng(1)
    tree.insert_point_cloud(rng.uniform(-1, 1, (200, 3)), [0, 0, 0])
    return tree


@pytest.mark.parametrize("kind", ["bt", "ot"])
def test_bytes_after_a_map_file_are_refused(small_tree, tmp_path, kind):
    path = tmp_path / f"map.{kind}"
    (small_tree.write_binary if kind == "bt" else small_tree.write)(path)
    read = earcore.OcTree.read_binary if kind == "bt" else earcore.OcTree.read
    whole = path.read_bytes()
    assert read(path).size() > 0
    for tail in (b"\0", b"\n", b"junk", whole):  # a stray byte, or two trees in one file
        path.write_bytes(whole + tail)
        with pytest.raises(earcore.MapFormatError, match=f"{len(tail)} bytes after"):
            read(path)


def test_octomaps_own_files_have_nothing_after_the_tree(octomap, tmp_path):
    """The rule matches OctoMap: what it writes ends with the tree, and reads here."""
    tree = octomap.OcTree(0.1)
    tree.updateNode(np.array([0.5, 0.5, 0.5]), True)
    for name, write, read in (("a.bt", "writeBinary", earcore.OcTree.read_binary), ("a.ot", "write", earcore.OcTree.read)):
        path = tmp_path / name
        getattr(tree, write)(str(path))
        assert read(path).size() == tree.size()


# ---- arrays that are not plain real numbers -------------------------------------------


BAD_ARRAYS = {
    "masked": (np.ma.masked_array(np.ones((2, 3)), mask=[[0, 1, 0], [0, 0, 0]]), "masked array"),
    "masked, nothing masked": (np.ma.masked_array(np.ones((2, 3))), "masked array"),
    "complex": (np.ones((2, 3)) + 1j, "complex"),
    "complex, zero imaginary": (np.ones((2, 3), dtype=complex), "complex"),
    "object": (np.ones((2, 3)).astype(object), "object"),
    "bool": (np.ones((2, 3), dtype=bool), "booleans"),
    "strings": (np.array([["1", "2", "3"]]), "strings"),
}


@pytest.mark.parametrize("name", list(BAD_ARRAYS))
def test_arrays_that_are_not_real_numbers_are_refused(name, small_tree):
    array, message = BAD_ARRAYS[name]
    before = small_tree.leaf_keys()
    with pytest.raises(TypeError, match=f"points.*{message}"):
        small_tree.insert_point_cloud(array, [0, 0, 0])
    with pytest.raises(TypeError, match=f"points.*{message}"):
        small_tree.is_occupied(array)
    with pytest.raises(TypeError, match=f"vertices.*{message}"):
        earcore.fit_body(array, 0.0, "auto")
    with pytest.raises(TypeError, match=f"sensor_origin.*{message}"):
        small_tree.insert_point_cloud([[1, 0, 0]], array[0])
    for a, b in zip(before, small_tree.leaf_keys()):
        np.testing.assert_array_equal(a, b)


# ---- URDF primitives with negative sizes ----------------------------------------------


def _urdf(tmp_path, geometry: str):
    path = tmp_path / "r.urdf"
    path.write_text(
        '<?xml version="1.0"?><robot name="r"><link name="base">'
        f"<collision><geometry>{geometry}</geometry></collision></link></robot>"
    )
    return path


@pytest.mark.parametrize(
    "geometry, element",
    [
        ('<box size="0.1 -0.2 0.3"/>', "box size"),
        ('<cylinder radius="-0.05" length="0.2"/>', "cylinder radius"),
        ('<cylinder radius="0.05" length="-0.2"/>', "cylinder length"),
        ('<sphere radius="-0.1"/>', "sphere radius"),
        ('<capsule radius="0.05" length="-1"/>', "capsule length"),
    ],
)
def test_negative_primitive_sizes_are_refused(tmp_path, geometry, element):
    with pytest.raises(urdf.UrdfError, match=f"link 'base' collision {element} must not be negative"):
        urdf.parse_urdf(_urdf(tmp_path, geometry))


def _stl(path, triangles):
    """An ASCII STL of the given triangles (each three vertices)."""
    lines = ["solid t"]
    for tri in triangles:
        lines += ["facet normal 0 0 1", "outer loop", *[f"vertex {x} {y} {z}" for x, y, z in tri], "endloop", "endfacet"]
    path.write_text("\n".join([*lines, "endsolid t"]))


def test_mesh_scales_mirror_but_never_flatten(tmp_path):
    """A negative scale mirrors the mesh (its vertices are the mirrored ones); a zero
    scale would flatten it and is refused."""
    _stl(tmp_path / "m.stl", [[(1, 2, 3), (4, 5, 6), (7, 8, 9)]])
    mirrored = urdf.parse_urdf(_urdf(tmp_path, '<mesh filename="m.stl" scale="-1 2 1"/>'))
    np.testing.assert_array_equal(mirrored.vertices["base"], [[-1, 4, 3], [-4, 10, 6], [-7, 16, 9]])
    with pytest.raises(urdf.UrdfError, match="mesh scale must not be zero"):
        urdf.parse_urdf(_urdf(tmp_path, '<mesh filename="m.stl" scale="1 0 1"/>'))


def test_zero_sized_primitives_stay_allowed(tmp_path):
    robot = urdf.parse_urdf(_urdf(tmp_path, '<box size="0.2 0 0.4"/>'))
    np.testing.assert_allclose(np.ptp(robot.vertices["base"], axis=0), [0.2, 0, 0.4])


def test_cloud_helpers_refuse_what_the_binding_would_misread():
    """Depth images, per-point values and voxel lookups are converted in Python or by
    numpy directly: masked and complex inputs are refused there too."""
    from earcore import cloud

    depth = np.ma.masked_array(np.ones((4, 5)), mask=np.eye(4, 5, dtype=bool))
    with pytest.raises(TypeError, match="depth is a masked array"):
        cloud.depth_to_points(depth, 100.0, 100.0, 2.0, 2.0)
    points = np.random.default_rng(0).uniform(size=(10, 3))
    with pytest.raises(TypeError, match="values must be real numbers"):
        cloud.voxel_downsample(points, 0.5, values=np.ones(10) * 1j)
    with pytest.raises(TypeError, match="points is a masked array"):
        cloud.voxel_codes(np.ma.masked_array(points), 0.1)
    # Rows of three are points; a transposed or wider array is not read as some.
    for shape_wrong in (points.T, np.zeros((30, 4))):
        with pytest.raises(ValueError, match=r"points must be an \(N, 3\) array"):
            cloud.voxel_codes(shape_wrong, 0.1)
        with pytest.raises(ValueError, match=r"centres must be an \(N, 3\) array"):
            cloud.voxel_means(shape_wrong, points, 0.1)
    assert cloud.voxel_codes([], 0.1).shape == (0,)
    assert cloud.voxel_means([], points, 0.1).shape == (0, 3)
    with pytest.raises(TypeError, match="box_min must be real numbers"):
        cloud.box_voxel_centres(np.zeros(3, dtype=complex), np.ones(3), 0.5)
    # Plain input is read as before: the unmasked image gives every pixel's point.
    assert len(cloud.depth_to_points(depth.data, 100.0, 100.0, 2.0, 2.0)) == 20
