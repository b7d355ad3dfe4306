"""Errors a user can act on: misaligned arrays are simply read,
messages name the parameter with numbers of sane length and no Rust internals, and
pickling either works (OcTree) or says plainly that it does not."""

from __future__ import annotations

import copy
import pickle
import re

import numpy as np
import pytest

import earcore
from earcore import _earcore


def misaligned(a: np.ndarray) -> np.ndarray:
    """A C-contiguous float64 copy of `a` whose data starts one byte off alignment."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    raw = np.zeros(a.nbytes + 1, dtype=np.uint8)[1:]
    out = raw.view(np.float64).reshape(a.shape)
    out[...] = a
    assert out.flags.c_contiguous and not out.flags.aligned
    return out


@pytest.fixture
def scene():
    rng = np.random.default_rng(4)
    return rng.uniform(-1, 1, (300, 3)) + [0, 0, 2]


def test_misaligned_arrays_are_read_like_aligned_ones(scene):
    """numpy's ascontiguousarray keeps such arrays as they are; the binding copies them
    rather than refusing them as "not contiguous")."""
    a, b = earcore.OcTree(0.05), earcore.OcTree(0.05)
    a.insert_point_cloud(scene, [0, 0, 0])
    b.insert_point_cloud(misaligned(scene), misaligned(np.zeros(3)))
    for x, y in zip(a.leaf_keys(), b.leaf_keys()):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.is_occupied(scene), a.is_occupied(misaligned(scene)))
    np.testing.assert_array_equal(
        a.cast_ray([0, 0, 0], [0, 0, 1])[1], a.cast_ray(misaligned(np.zeros(3)), misaligned(np.array([0, 0, 1.0])))[1]
    )
    # The other converters: a rigid fit (points), a pose and plain numbers.
    shifted = scene + [0.1, 0.2, 0.3]
    np.testing.assert_allclose(_earcore.rigid_fit(misaligned(scene), misaligned(shifted)), _earcore.rigid_fit(scene, shifted))
    target = _earcore.PlaneTarget(scene, np.tile([0, 0, 1.0], (len(scene), 1)))
    with_pose = _earcore.icp_point_to_plane_raw(scene, target, misaligned(np.eye(4)), max_iterations=1)
    np.testing.assert_allclose(with_pose.transform, _earcore.icp_point_to_plane_raw(scene, target, np.eye(4), max_iterations=1).transform)
    f = _earcore.Follower(misaligned(np.ones(3)), misaligned(np.full(3, 2.0)), 1.0)
    g = _earcore.Follower(np.ones(3), np.full(3, 2.0), 1.0)
    q, last = np.zeros(3), np.zeros(3)
    np.testing.assert_array_equal(f.command(q, last, np.ones(3), np.ones(3), 0.1), g.command(q, last, np.ones(3), np.ones(3), 0.1))


# ---- messages ---------------------------------------------------------------------------

#: Signs of Rust leaking through a message: debug structs, Option/Result wrappers,
#: type names, panics.
RUST_INTERNALS = re.compile(r"Some\(|None\)|Ok\(|Err\(|\bf64\b|\bf32\b|\busize\b|Params \{|unwrap|panicked|::")


def message_of(call) -> str:
    with pytest.raises((ValueError, TypeError, earcore.EarcoreError)) as info:
        call()
    return str(info.value)


def check_message(message: str, *names: str) -> None:
    assert len(message) < 300, message
    # No number longer than %.6g would print (a huge or tiny float in full).
    assert not re.search(r"\d{12,}", message), message
    assert not RUST_INTERNALS.search(message), message
    for name in names:
        assert name in message, f"{name!r} not named in {message!r}"


@pytest.fixture
def tree(scene):
    t = earcore.OcTree(0.05)
    t.insert_point_cloud(scene, [0, 0, 0])
    return t


def _plane():
    return _earcore.PlaneTarget(np.zeros((3, 3)), np.ones((3, 3)))


BAD_CALLS = {
    "huge resolution": (lambda t: earcore.OcTree(1e308), ["resolution", "1e308"]),
    "tiny resolution": (lambda t: earcore.OcTree(1e-100), ["resolution", "1e-100"]),
    "surface resolution": (lambda t: earcore.SurfaceMap(1e-300), ["resolution", "1e-300"]),
    "surface prob_hit": (lambda t: earcore.SurfaceMap(0.05, prob_hit=1.5), ["prob_hit", "1.5"]),
    "surface similar": (lambda t: earcore.SurfaceMap(0.05, similar=-1e300), ["similar", "-1e300"]),
    "surface position_memory": (lambda t: earcore.SurfaceMap(0.05, position_memory=0), ["position_memory"]),
    "surface order": (lambda t: earcore.SurfaceMap(0.05, prob_hit=0.9, clamping_max=0.8), ["prob_hit", "clamping_max"]),
    "tree probability": (lambda t: earcore.OcTree(0.05, prob_hit=1e300), ["prob_hit", "1e300"]),
    "far point": (lambda t: t.insert_point_cloud([[1e300, 0, 0]], [0, 0, 0]), ["point", "1e300", "1638.4"]),
    "far origin": (lambda t: t.insert_point_cloud([[1, 0, 0]], [0, 1e200, 0]), ["origin", "1e200"]),
    "far update": (lambda t: t.update_node([1e-300, 1e100, 0], True), ["point", "1e100"]),
    "nan point": (lambda t: t.insert_point_cloud([[0, 0, 1], [np.nan, 1e300, 0]], [0, 0, 0]), ["point 1", "not finite"]),
    "max_range": (lambda t: t.insert_point_cloud([[1, 0, 0]], [0, 0, 0], max_range=-1e300), ["max_range", "-1e300"]),
    "ray max_range": (lambda t: t.cast_ray([0, 0, 0], [1, 0, 0], max_range=-1e-300), ["max_range", "-1e-300"]),
    "direction": (lambda t: t.cast_ray([0, 0, 0], [np.inf, 0, 1e300]), ["direction", "1e300"]),
    "delta": (lambda t: t.update_log_odds([[0, 0, 0]], 1e300), ["delta", "1e300"]),
    "end_frame": (lambda t: t.end_frame(-1e300), ["dt", "-1e300"]),
    "alpha": (lambda t: setattr(t, "danger_alpha", -1e300), ["alpha", "-1e300"]),
    "points shape": (lambda t: t.is_occupied(np.zeros((4, 2))), ["points", "(4, 2)"]),
    "points 1-d": (lambda t: t.is_occupied(np.zeros(5)), ["points", "(5,)"]),
    "points strings": (lambda t: t.is_occupied([["a", "b", "c"]]), ["points"]),
    "points ragged": (lambda t: t.is_occupied([[1, 2, 3], [1, 2]]), ["points"]),
    "origin shape": (lambda t: t.insert_point_cloud([[1, 0, 0]], [0, 0]), ["sensor_origin"]),
    "bbx": (lambda t: t.leaves([0, 0], [1, 1, 1]), ["bbx_min"]),
    "box nan": (lambda t: t.leaves_at_full_depth([np.nan, 0, 0], [1, 1, 1]), ["box", "NaN"]),
    "pose shape": (lambda t: _earcore.icp_point_to_plane_raw(np.zeros((3, 3)), _plane(), np.eye(3)), ["initial", "(3, 3)"]),
    "fit padding": (lambda t: earcore.fit_body(np.zeros((3, 3)), -1e300, "auto"), ["padding", "-1e300"]),
    "fit vertex": (lambda t: earcore.fit_body([[0, 0, 0], [1e300, np.inf, 0]], 0.0, "auto"), ["vertex 1", "not finite"]),
    "surface origin": (lambda t: earcore.SurfaceMap(0.05).insert(np.ones((2, 3)), [0, 0], 0.03), ["sensor_origin", "2 values"]),
    "beam_spacing": (lambda t: earcore.SurfaceMap(0.05).insert(np.ones((2, 3)), [0, 0, 0], 1e300), ["beam_spacing", "1e300"]),
    "surface position_memory u16": (lambda t: earcore.SurfaceMap(0.05, position_memory=65536), ["position_memory", "65535", "65536"]),
    "surface position_memory huge": (lambda t: earcore.SurfaceMap(0.05, position_memory=2**70), ["position_memory", "65535"]),
    "depth image shape": (lambda t: earcore.depth_to_points(np.ones((4, 5, 1)), 5.0, 5.0, 2.0, 2.0), ["depth", "(4, 5, 1)"]),
    "depth intrinsics": (lambda t: earcore.depth_to_points(np.ones((4, 5)), 0.0, 5.0, 2.0, 2.0), ["fx = 0", "fy = 5"]),
    "outlier k": (lambda t: earcore.remove_statistical_outliers(np.zeros((9, 3)), 0), ["k = 0", "std_ratio = 2"]),
    "refined poses": (lambda t: earcore.refine_camera_poses([np.zeros((9, 3))] * 2, [np.eye(4), np.eye(3)]), ["base_from_cameras[1]", "(3, 3)"]),
    "refined reference": (
        lambda t: earcore.refine_camera_poses([np.zeros((9, 3))] * 2, [np.diag([2.0, 2.0, 2.0, 1.0]), np.eye(4)]),
        ["base_from_cameras[0]", "rigid"],
    ),
}


@pytest.mark.parametrize("case", list(BAD_CALLS))
def test_messages_name_the_parameter_in_a_few_characters(tree, case):
    call, names = BAD_CALLS[case]
    check_message(message_of(lambda: call(tree)), *names)


def test_map_format_errors_are_short(tmp_path):
    path = tmp_path / "m.ot"
    path.write_bytes(b"# Octomap OcTree file\nid OcTree\nsize 1\nres " + b"9" * 400 + b"\ndata\n")
    with pytest.raises(earcore.MapFormatError) as info:
        earcore.OcTree.read(path)
    check_message(str(info.value), "resolution")


# ---- pickling ---------------------------------------------------------------------------


def _same_tree(a: earcore.OcTree, b: earcore.OcTree, tmp_path) -> None:
    a.write(tmp_path / "a.ot")
    b.write(tmp_path / "b.ot")
    assert (tmp_path / "a.ot").read_bytes() == (tmp_path / "b.ot").read_bytes()
    for name in ("resolution", "prob_hit", "prob_miss", "clamping_min", "clamping_max", "occupancy_threshold", "danger_alpha", "decay_mode"):
        assert getattr(a, name) == getattr(b, name), name
    for x, y in zip(a.danger_voxels(), b.danger_voxels()):
        np.testing.assert_array_equal(x, y)
    for x, y in zip(a.current_obstacles(), b.current_obstacles()):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("protocol", range(2, pickle.HIGHEST_PROTOCOL + 1))
def test_an_octree_pickles_with_its_danger_and_sensor_model(scene, tmp_path, protocol):
    """The reference is `copy()`, which clones the whole tree: an unpickled tree must
    equal it now and evolve identically, the open frame's hits and sightings included."""
    t = earcore.OcTree(0.05, prob_hit=0.8, clamping_max=0.95, danger_alpha=0.7, decay_mode="always")
    t.insert_point_cloud(scene, [0, 0, 0])
    t.end_frame(0.1)
    t.insert_point_cloud(scene[:40] + 0.3, [0, 0, 0])  # a frame left open
    reference = t.copy()
    back = pickle.loads(pickle.dumps(t, protocol=protocol))
    assert type(back) is earcore.OcTree
    _same_tree(back, reference, tmp_path)
    assert back.end_frame(0.2).__repr__() == reference.end_frame(0.2).__repr__()
    _same_tree(back, reference, tmp_path)
    # Independent of the original.
    back.clear()
    assert t.size() > 0
    # deepcopy (through __deepcopy__) and pickle agree.
    _same_tree(copy.deepcopy(t), pickle.loads(pickle.dumps(t)), tmp_path)


def test_an_empty_octree_pickles(tmp_path):
    t = earcore.OcTree(0.2)
    _same_tree(pickle.loads(pickle.dumps(t)), t, tmp_path)


def test_damaged_pickles_raise_map_format_errors(tree):
    state = tree.__reduce__()[1][0]
    rebuild = tree.__reduce__()[0]
    for bad in (state[:-1], state + b"\0", b"not a state", state[:40]):
        with pytest.raises(earcore.MapFormatError):
            rebuild(bad)


@pytest.mark.parametrize(
    "make",
    [
        lambda: earcore.SurfaceMap(0.05),
        lambda: earcore.OcTree(0.1).insert_point_cloud([[1, 0, 0]], [0, 0, 0]),
    ],
    ids=["SurfaceMap", "InsertReport"],
)
def test_what_cannot_be_pickled_says_so(make):
    with pytest.raises(TypeError, match="pickle"):
        pickle.dumps(make())
