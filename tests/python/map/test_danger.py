"""Danger decay (Paper II, Eq. 1) checked against the rule itself, frame by frame.

One voxel sits on the x axis. Each frame it is either hit (a scan ends in it), seen
free (a scan passes through it to a wall behind), or occluded (the only scan ends
in front of it). The reference applies C ← C + ln(C)·dt·α, clamped at 0, in float64
and stores float32 as the map does.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import earcore

RES = 0.1
ORIGIN = np.array([0.05, 0.05, 0.05])
VOXEL = np.array([[1.05, 0.05, 0.05]])
BEHIND = np.array([[2.05, 0.05, 0.05]])
IN_FRONT = np.array([[0.55, 0.05, 0.05]])
HIT = np.float32(0.999)


def frame(tree, event: str, dt: float):
    scan = {"hit": VOXEL, "free": BEHIND, "occluded": IN_FRONT}[event]
    tree.insert_point_cloud(scan, ORIGIN)
    return tree.end_frame(dt)


def reference_step(c: np.float32, event: str, mode: str, dt: float, alpha: float) -> np.float32:
    if event == "hit":
        return HIT
    if c == 0 or (mode == "observed" and event != "free"):
        return c
    nxt = float(c) + np.log(float(c)) * dt * alpha
    return np.float32(nxt) if nxt > 0 else np.float32(0.0)


@settings(max_examples=150, deadline=None)
@given(
    events=st.lists(st.sampled_from(["hit", "free", "occluded"]), min_size=1, max_size=60),
    dt=st.floats(0.005, 0.5),
    alpha=st.floats(0.05, 3.0),
    mode=st.sampled_from(["observed", "always"]),
)
def test_danger_follows_equation_1(events, dt, alpha, mode):
    tree = earcore.OcTree(RES, danger_alpha=alpha, decay_mode=mode)
    c = np.float32(0.0)
    previous = None
    for event in ["hit"] + events:
        frame(tree, event, dt)
        c = reference_step(c, event, mode, dt, alpha)
        got = tree.danger(VOXEL)[0]
        assert got == pytest.approx(c, rel=1e-6, abs=1e-7)
        assert 0.0 <= got <= HIT
        if event == "hit":
            assert got == HIT, "a hit resets the danger to 0.999"
        elif previous is not None:
            assert got <= previous, "without a hit danger never grows"
            if event == "occluded" and mode == "observed":
                assert got == previous, "an occluded voxel keeps its danger"
        if got == 0:
            centres, _, _ = tree.danger_voxels()
            assert not np.any(np.all(np.isclose(centres, VOXEL), axis=1)), "a voxel at 0 leaves the danger map"
        previous = got


def test_decay_time_matches_the_paper():
    """α = 0.3 at 15 Hz: from a single hit to no danger in 21.4 s ± one frame."""
    dt = 1 / 15
    tree = earcore.OcTree(RES, danger_alpha=0.3)
    frame(tree, "hit", dt)
    frames = 0
    while tree.danger(VOXEL)[0] > 0:
        frame(tree, "free", dt)
        frames += 1
        assert frames < 1000
    assert abs(frames * dt - 21.4) <= dt + 1e-9
    # Slow at first, fast at the end (the shape of Eq. 1).
    trace = []
    frame(tree, "hit", dt)
    for _ in range(frames):
        trace.append(float(tree.danger(VOXEL)[0]))
        frame(tree, "free", dt)
    steps = -np.diff(trace)
    assert steps[0] < steps[len(steps) // 2] < steps[-2]


def test_observed_versus_always_with_occlusion():
    trees = {mode: earcore.OcTree(RES, decay_mode=mode) for mode in ("observed", "always")}
    for tree in trees.values():
        frame(tree, "hit", 0.1)
        for _ in range(50):
            frame(tree, "occluded", 0.1)
    assert trees["observed"].danger(VOXEL)[0] == HIT
    assert trees["always"].danger(VOXEL)[0] < HIT


def test_hit_wins_over_free_in_the_same_frame():
    tree = earcore.OcTree(RES)
    frame(tree, "hit", 0.1)
    for _ in range(20):
        frame(tree, "free", 0.1)
    assert tree.danger(VOXEL)[0] < HIT
    tree.insert_point_cloud(BEHIND, ORIGIN)  # one camera sees through it...
    tree.insert_point_cloud(VOXEL, ORIGIN)  # ...another hits it
    tree.end_frame(0.1)
    assert tree.danger(VOXEL)[0] == HIT


def test_current_obstacles_are_the_last_frames_hits():
    tree = earcore.OcTree(RES)
    tree.insert_point_cloud(np.vstack([VOXEL, BEHIND]), ORIGIN)
    assert len(tree.current_obstacles()[0]) == 0, "nothing until the frame is closed"
    tree.end_frame(0.1)
    centres, sizes = tree.current_obstacles()
    np.testing.assert_allclose(centres[np.lexsort(centres.T[::-1])], np.vstack([VOXEL, BEHIND]), atol=1e-9)
    assert np.all(sizes == RES)
    frame(tree, "occluded", 0.1)
    centres, _ = tree.current_obstacles()
    np.testing.assert_allclose(centres, IN_FRONT, atol=1e-9)


def test_frame_cost_follows_the_active_set_not_the_map():
    """end_frame only visits dangerous voxels: its report counts them, not the map."""
    tree = earcore.OcTree(0.05)
    points, origin = earcore.synthetic.benchmark_frame()
    tree.insert_point_cloud(points, origin)
    first = tree.end_frame(0.1)
    assert first.hit == first.active < tree.num_leaf_nodes()
    tree.insert_point_cloud(VOXEL + [0, 0, 1.0], ORIGIN)
    second = tree.end_frame(0.1)
    assert second.hit == 1 and second.decayed <= second.active
    # Counted exactly: one voxel hit, then a frame whose ray sees it free (from the
    # other side, ending two voxels beyond it) and hits a new one.
    small = earcore.OcTree(0.05)
    small.insert_point_cloud(VOXEL, ORIGIN)
    report = small.end_frame(0.1)
    assert (report.hit, report.decayed, report.active) == (1, 0, 1)
    small.insert_point_cloud(VOXEL - [0.1, 0, 0], VOXEL[0] + [0.3, 0, 0])
    report = small.end_frame(0.1)
    assert (report.hit, report.decayed, report.active) == (1, 1, 2)
    _, _, values = small.danger_voxels()
    assert sorted(values.tolist())[1] == pytest.approx(0.999) and 0.99 < min(values) < 0.999


def test_free_rays_clear_space_without_hits():
    """`insert_free_rays`: the same rays as `insert_point_cloud`, minus the hits; the
    danger of a voxel they see free decays."""
    rng = np.random.default_rng(9)
    origin = np.array([0.1, -0.2, 1.5])
    points = rng.uniform([-1, -1, 0], [1, 1, 0.3], (2000, 3))
    free_only, full = earcore.OcTree(0.05), earcore.OcTree(0.05)
    free_only.insert_free_rays(points, origin)
    full.insert_point_cloud(points, origin)
    fc, _, fl = free_only.leaves()
    gc, _, gl = full.leaves()
    assert (fl < 0).all()  # nothing occupied
    assert (free_only.is_occupied(gc[gl < 0]) == 0).all()  # every free cell of the full scan
    # End cells are known only where another ray crossed them.
    assert (free_only.is_occupied(gc[gl > 0]) != 1).all() and (free_only.is_occupied(gc[gl > 0]) == -1).any()
    # Danger: hit once, then seen free through free rays only.
    tree = earcore.OcTree(0.05)
    blob = np.array([[0.0, 0.0, 0.5]])
    tree.insert_point_cloud(blob, origin)
    tree.end_frame(1 / 15)
    behind = origin + 1.5 * (blob[0] - origin)
    tree.insert_free_rays(behind[None], origin)
    tree.end_frame(1 / 15)
    assert 0 < tree.danger(blob)[0] < 0.999


def test_clear_forgets_the_danger_but_keeps_its_parameters():
    """After `clear` a map behaves as a fresh one with the same sensor model and danger
    parameters (`danger_alpha`, `decay_mode` set by the user stay)."""
    rng = np.random.default_rng(4)
    origin = np.array([0.0, 0.0, 1.5])
    scans = [rng.uniform([-1, -1, 0], [1, 1, 0.3], (500, 3)) for _ in range(3)]

    def configured():
        tree = earcore.OcTree(0.05, prob_hit=0.8)
        tree.danger_alpha, tree.decay_mode = 0.9, "always"
        return tree

    used = configured()
    for scan in scans:
        used.insert_point_cloud(scan, origin)
        used.end_frame(0.5)
    used.clear()
    assert used.size() == 0 and len(used.danger_voxels()[0]) == 0 and len(used.current_obstacles()[0]) == 0
    assert (used.danger_alpha, used.decay_mode, used.prob_hit) == (0.9, "always", 0.8)
    fresh = configured()
    for tree in (used, fresh):
        tree.insert_point_cloud(scans[0], origin)
        tree.end_frame(0.5)
        tree.insert_point_cloud(scans[1][:100], origin)
        tree.end_frame(2.0)
    a, b = used.danger_voxels(), fresh.danger_voxels()
    assert all(np.array_equal(x, y) for x, y in zip(a, b)) and len(a[0]) > 0
