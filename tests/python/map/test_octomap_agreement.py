"""earcore's OcTree against OctoMap itself (pyoctomap) on random depth scenes.

Every scene is scanned from three viewpoints into one tree (so updates also hit
existing, clamped and pruned nodes). The comparison is cell for cell: every leaf
OctoMap reports (its own iterator, its own occupancy test) is looked up in earcore,
and the two full serialisations (.ot) must be byte-identical.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import earcore
from reference import octomap_leaves, scene_scans

#: The issue allows 0.01 % of cells to differ; none do, because earcore replicates
#: OctoMap's float/double arithmetic (float points, double DDA) and update rules.
MAX_DIFFERENT_FRACTION = 1e-4

COMBOS = [(None, False), (2.0, False), (None, True), (2.0, True)]


def build_both(octomap, scans, resolution, max_range, discretize):
    ref = octomap.OcTree(resolution)
    ours = earcore.OcTree(resolution)
    for pts, origin in scans:
        ref.insertPointCloud(pts, origin, max_range=-1.0 if max_range is None else max_range, discretize=discretize)
        ours.insert_point_cloud(pts, origin, max_range=max_range, discretize=discretize)
    return ref, ours


def ot_bytes(tree, tmp_path) -> bytes:
    path = tmp_path / "ours.ot"
    tree.write(path)
    return path.read_bytes()


@pytest.mark.parametrize("resolution", [0.05, 0.02])
@pytest.mark.parametrize("seed", range(24))
def test_random_scene_matches_octomap_cell_for_cell(octomap, tmp_path, seed, resolution):
    max_range, discretize = COMBOS[seed % len(COMBOS)]
    scans = scene_scans(seed)
    ref, ours = build_both(octomap, scans, resolution, max_range, discretize)

    centres, depths, ref_occupied = octomap_leaves(ref)
    assert len(centres) > 1000, "the scene should produce a real map"
    assert ours.num_leaf_nodes() == len(centres) == ref.getNumLeafNodes()
    assert ours.size() == ref.size()

    # Occupancy of every known cell, looked up at OctoMap's leaf centres.
    our_occupied = ours.is_occupied(centres)
    assert (our_occupied >= 0).all(), "a cell OctoMap knows is unknown to earcore"
    different = np.count_nonzero(our_occupied.astype(bool) != ref_occupied)
    assert different <= MAX_DIFFERENT_FRACTION * len(centres), f"{different} of {len(centres)} cells differ"

    # Same leaves at the same depths (pruning identical), same log-odds everywhere.
    our_centres, our_sizes, _ = ours.leaves()
    ref_sizes = resolution * 2.0 ** (16 - depths)
    order = lambda c, s: np.lexsort((s, c[:, 2], c[:, 1], c[:, 0]))  # noqa: E731
    a, b = order(our_centres, our_sizes), order(centres, ref_sizes)
    np.testing.assert_allclose(our_centres[a], centres[b], atol=1e-6)
    np.testing.assert_allclose(our_sizes[a], ref_sizes[b], rtol=1e-12)
    assert ot_bytes(ours, tmp_path) == ref.write(), "full serialisations differ"


@pytest.mark.parametrize("resolution", [0.05, 0.02])
def test_full_kinect_frame_matches_octomap(octomap, tmp_path, resolution):
    points, origin = earcore.synthetic.benchmark_frame()
    assert len(points) > 200_000
    ref, ours = build_both(octomap, [(points, origin)], resolution, None, False)
    assert ot_bytes(ours, tmp_path) == ref.write()
    centres, _, ref_occupied = octomap_leaves(ref)
    assert np.array_equal(ours.is_occupied(centres).astype(bool), ref_occupied)


def test_returns_off_the_map_beyond_max_range_are_cut_as_octomap_cuts_them(octomap, tmp_path):
    """OctoMap never keys a point beyond the maximum range (its ray ends there), so such
    a point may lie off the map: a far return seen on a fine map. Points off the map
    within the range, or in a scan to be discretised (which keys every point), are
    refused, the map unchanged."""
    rng = np.random.default_rng(5)
    resolution, origin, max_range = 0.01, np.array([0.1, 0.2, 0.3]), 2.5  # the map spans ±327.68 m
    near = origin + rng.normal(size=(3000, 3)) * 0.8
    directions = rng.normal(size=(200, 3))
    far = origin + directions / np.linalg.norm(directions, axis=1, keepdims=True) * rng.uniform(400, 5000, (200, 1))
    scan = rng.permutation(np.vstack([near, far]))
    ref = octomap.OcTree(resolution)
    ref.insertPointCloud(scan, origin, max_range=max_range)
    ours = earcore.OcTree(resolution)
    ours.insert_point_cloud(scan, origin, max_range=max_range)
    assert ours.size() == ref.size() > 1000
    assert ot_bytes(ours, tmp_path) == ref.write()
    free_only = earcore.OcTree(resolution)
    free_only.insert_free_rays(scan, origin, max_range=max_range)
    assert free_only.size() > 1000 and not free_only.occupied_voxels()[0].size
    before = ot_bytes(ours, tmp_path)
    for points, kwargs in ((scan, dict(max_range=2 * 5000.0)), (scan, dict(max_range=max_range, discretize=True))):
        with pytest.raises(earcore.OutOfMapError, match="outside the map"):
            ours.insert_point_cloud(points, origin, **kwargs)
    assert ot_bytes(ours, tmp_path) == before


def test_thread_count_does_not_change_the_map(tmp_path):
    points, origin = earcore.synthetic.benchmark_frame()
    maps = []
    for n in (1, 2, 3):
        earcore.set_num_threads(n)
        tree = earcore.OcTree(0.05)
        tree.insert_point_cloud(points, origin)
        maps.append(ot_bytes(tree, tmp_path))
    earcore.set_num_threads(0)
    assert maps[0] == maps[1] == maps[2]


#: Builds maps in a child process and writes their .ot files (argv: directory).
_SCALAR_WALK_SCRIPT = """
import sys, numpy as np, earcore
from reference import scene_scans
points, origin = earcore.synthetic.benchmark_frame()
for resolution in (0.05, 0.02):
    tree = earcore.OcTree(resolution)
    tree.insert_point_cloud(points, origin)
    tree.write(f"{sys.argv[1]}/frame-{resolution}.ot")
    for seed, (max_range, discretize) in enumerate([(None, False), (2.0, False), (1.0, True)]):
        tree = earcore.OcTree(resolution)
        for pts, o in scene_scans(seed):
            tree.insert_point_cloud(pts, o, max_range=max_range, discretize=discretize)
        tree.write(f"{sys.argv[1]}/scene{seed}-{resolution}.ot")
"""


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            return {flag for line in f if line.startswith("flags") for flag in line.split(":", 1)[1].split()}
    except OSError:
        return set()


@pytest.mark.skipif("avx2" not in _cpu_flags(), reason="the batched ray walk needs AVX2 (x86-64 Linux)")
def test_scalar_walk_fallback_builds_the_same_maps(tmp_path):
    """The batched ray walks (AVX-512 where the CPU has it, AVX2) and the scalar walk
    CPUs without AVX2 use agree byte for byte; `EARCORE_NO_AVX512` forces the AVX2
    walk, `EARCORE_NO_AVX2` the scalar one (read once per process)."""
    tests = os.path.dirname(os.path.dirname(os.path.dirname(__file__)))  # where reference.py is
    plain = {k: v for k, v in os.environ.items() if k not in ("EARCORE_NO_AVX2", "EARCORE_NO_AVX512")}
    walks = [("batched", {}), ("scalar", {"EARCORE_NO_AVX2": "1"})]
    if "avx512f" in _cpu_flags():
        walks.append(("avx2", {"EARCORE_NO_AVX512": "1"}))
    for name, extra in walks:
        (tmp_path / name).mkdir()
        env = {**plain, **extra}
        subprocess.run(
            [sys.executable, "-c", _SCALAR_WALK_SCRIPT, str(tmp_path / name)], cwd=tests, env=env, check=True, timeout=300
        )
    files = sorted(p.name for p in (tmp_path / "batched").iterdir())
    assert len(files) == 8
    for name, _ in walks[1:]:
        for f in files:
            assert (tmp_path / "batched" / f).read_bytes() == (tmp_path / name / f).read_bytes(), (name, f)


def test_update_node_matches_octomap(octomap, tmp_path):
    """Single-cell updates (hits, misses, raw log-odds) and prune, in the same order."""
    rng = np.random.default_rng(7)
    ref, ours = octomap.OcTree(0.1), earcore.OcTree(0.1)
    cells = rng.integers(-6, 6, size=(400, 3)) * 0.1 + 0.05
    for i, p in enumerate(cells):
        update = bool(rng.random() < 0.6) if i % 3 else float(rng.normal(0, 1.5))
        ref.updateNode(p, update)
        ours.update_node(p, update)
    assert ot_bytes(ours, tmp_path) == ref.write()
    # Updates prune as they go, so an explicit prune changes nothing.
    ours.prune()
    assert ot_bytes(ours, tmp_path) == ref.write()


def test_prune_collapses_what_lazy_updates_left(octomap, tmp_path):
    """OctoMap's lazy updates leave equal siblings unpruned; `prune` collapses them
    and nothing else: every cell keeps its value, and no collapsible node is left."""
    ref = octomap.OcTree(0.1)
    block = np.argwhere(np.ones((2, 2, 2))) * 0.1 + 0.05
    for p in np.concatenate([block, block + [0.4, 0.0, 0.0], [[1.05, 0.05, 0.05]]]):
        ref.updateNode(p, True, True)  # lazy: no pruning
    ref.updateInnerOccupancy()
    path = tmp_path / "lazy.ot"
    ref.write(str(path))
    ours = earcore.OcTree.read(path)
    assert ours.size() == ref.size()
    centres_before, sizes_before, values_before = ours.leaves()
    probes = np.concatenate([block, block + [0.4, 0.0, 0.0], [[1.05, 0.05, 0.05], [3.0, 3.0, 3.0]]])
    occupancy_before = ours.log_odds(probes)
    ours.prune()
    assert ours.size() == ref.size() - 16, "each full block of 8 equal leaves collapses into its parent"
    np.testing.assert_array_equal(ours.log_odds(probes), occupancy_before)
