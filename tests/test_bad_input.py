"""Bad input gets a clear exception, never a crash, and leaves the tree as it was."""

from __future__ import annotations

import numpy as np
import pytest

import earcore


@pytest.fixture
def tree():
    t = earcore.OcTree(0.05)
    rng = np.random.default_rng(0)
    t.insert_point_cloud(rng.uniform(-1, 1, (500, 3)) + [0, 0, 2], [0, 0, 0])
    t.end_frame(0.1)
    return t


def snapshot(tree, tmp_path):
    path = tmp_path / "snap.ot"
    tree.write(path)
    return path.read_bytes(), tree.danger_voxels()[2].tobytes()


GOOD = np.array([[1.0, 0.5, 0.2]])


@pytest.mark.parametrize(
    "points, error, message",
    [
        (np.array([[np.nan, 0, 0]]), ValueError, "not finite"),
        (np.array([[0, np.inf, 0]]), ValueError, "not finite"),
        (np.vstack([GOOD, [[0, 0, -np.inf]]]), ValueError, "point 1"),
        (np.zeros(3), ValueError, r"\(N, 3\)"),
        (np.zeros((4, 2)), ValueError, r"\(N, 3\)"),
        (np.zeros((2, 3, 1)), ValueError, r"\(N, 3\)"),
        (np.array([["a", "b", "c"]]), TypeError, "numbers"),
        (np.zeros((0, 3)), ValueError, "empty"),
        (np.array([[5000.0, 0, 0]]), earcore.OutOfMapError, "outside the map"),
        (np.array([[0, 0, -1638.41]]), earcore.OutOfMapError, "outside the map"),
    ],
)
def test_bad_points_raise_and_change_nothing(tree, tmp_path, points, error, message):
    before = snapshot(tree, tmp_path)
    with pytest.raises(error, match=message):
        tree.insert_point_cloud(points, [0, 0, 0])
    assert snapshot(tree, tmp_path) == before


@pytest.mark.parametrize(
    "kwargs, error",
    [
        (dict(sensor_origin=[np.nan, 0, 0]), ValueError),
        (dict(sensor_origin=[0, 0]), ValueError),
        (dict(sensor_origin=[1e6, 0, 0]), earcore.OutOfMapError),
        (dict(sensor_origin=[0, 0, 0], max_range=0.0), ValueError),
        (dict(sensor_origin=[0, 0, 0], max_range=-2.0), ValueError),
        (dict(sensor_origin=[0, 0, 0], max_range=float("nan")), ValueError),
    ],
)
def test_bad_scan_arguments(tree, tmp_path, kwargs, error):
    before = snapshot(tree, tmp_path)
    with pytest.raises(error):
        tree.insert_point_cloud(GOOD, **kwargs)
    assert snapshot(tree, tmp_path) == before


@pytest.mark.parametrize("resolution", [0.0, -0.05, float("nan"), float("inf")])
def test_bad_resolution(resolution):
    with pytest.raises(ValueError, match="resolution"):
        earcore.OcTree(resolution)


@pytest.mark.parametrize(
    "kwargs",
    [dict(prob_hit=1.0), dict(prob_miss=0.0), dict(clamping_min=0.9, clamping_max=0.2), dict(danger_alpha=-1.0), dict(decay_mode="sometimes")],
)
def test_bad_parameters(kwargs):
    with pytest.raises(ValueError):
        earcore.OcTree(0.05, **kwargs)


def test_other_calls_reject_bad_input(tree, tmp_path):
    before = snapshot(tree, tmp_path)
    with pytest.raises(ValueError):
        tree.cast_ray([0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        tree.cast_ray([0, 0, 0], [np.nan, 1, 0])
    with pytest.raises(earcore.OutOfMapError):
        tree.cast_ray([1e5, 0, 0], [1, 0, 0])
    with pytest.raises(ValueError):
        tree.cast_rays(np.zeros((3, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError):
        tree.end_frame(-0.1)
    with pytest.raises(ValueError):
        tree.end_frame(float("nan"))
    with pytest.raises(earcore.OutOfMapError):
        tree.update_node([1e5, 0, 0], True)
    with pytest.raises(ValueError):
        tree.update_node([0, 0, 0], float("nan"))
    with pytest.raises(TypeError):
        tree.update_node([0, 0, 0], "hit")
    with pytest.raises(ValueError):
        tree.is_occupied(np.zeros((5, 4)))
    with pytest.raises(earcore.OutOfMapError):
        tree.search([0, 0, 1e9])
    with pytest.raises(ValueError):
        tree.danger_alpha = float("inf")
    assert snapshot(tree, tmp_path) == before


def test_queries_accept_any_numeric_array_and_off_map_points(tree):
    pts = np.array([[0, 0, 2]], dtype=np.float32)
    assert tree.is_occupied(pts).dtype == np.int8
    assert tree.is_occupied([[0, 0, 2]]).shape == (1,)
    assert tree.is_occupied(np.asfortranarray(np.zeros((4, 3)))).shape == (4,)
    # Points off the map are simply unknown (and never dangerous) for queries.
    far = np.array([[1e7, 0, 0], [np.nan, 0, 0]])
    assert list(tree.is_occupied(far)) == [-1, -1]
    assert np.isnan(tree.log_odds(far)).all()
    assert list(tree.danger(far)) == [0.0, 0.0]
    assert tree.is_occupied(np.zeros((0, 3))).shape == (0,)


def test_exceptions_are_earcore_errors():
    assert issubclass(earcore.OutOfMapError, earcore.EarcoreError)
    assert issubclass(earcore.MapFormatError, earcore.EarcoreError)
