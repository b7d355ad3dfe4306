"""OctoMap's .bt and .ot files, both ways with OctoMap itself, and hostile input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import earcore
from reference import octomap_leaves, scene_scans


@pytest.fixture(scope="module")
def scan():
    return scene_scans(3, n_views=2)


def build(scans, resolution=0.05):
    tree = earcore.OcTree(resolution)
    for pts, origin in scans:
        tree.insert_point_cloud(pts, origin)
    return tree


def test_ot_round_trip_both_ways(octomap, tmp_path, scan):
    ours = build(scan)
    ours.write(tmp_path / "ours.ot")
    ref = octomap.OcTree(0.1).read(str(tmp_path / "ours.ot"))
    assert ref is not None and ref.size() == ours.size()
    centres, _, occupied = octomap_leaves(ref)
    assert np.array_equal(ours.is_occupied(centres).astype(bool), occupied)
    some = centres[:: max(1, len(centres) // 2000)]
    np.testing.assert_array_equal(ours.log_odds(some), np.array([ref.search(c).getLogOdds() for c in some], np.float32))
    # OctoMap writes it back byte for byte; earcore reads OctoMap's own file.
    ref.write(str(tmp_path / "ref.ot"))
    assert (tmp_path / "ref.ot").read_bytes() == (tmp_path / "ours.ot").read_bytes()
    again = earcore.OcTree.read(tmp_path / "ref.ot")
    assert again.size() == ours.size()
    np.testing.assert_array_equal(again.log_odds(centres), ours.log_odds(centres))


def test_bt_round_trip_both_ways(octomap, tmp_path, scan):
    ours = build(scan)
    size_before = ours.size()
    ours.write_binary(tmp_path / "ours.bt")
    assert ours.size() == size_before, "writing .bt must not change the tree (OctoMap's does)"
    ref = octomap.OcTree(0.1)
    assert ref.readBinary(str(tmp_path / "ours.bt"))
    centres, _, occupied = octomap_leaves(ref)
    # .bt keeps maximum-likelihood occupancy only: compare occupied/free per cell.
    assert np.array_equal(ours.is_occupied(centres).astype(bool), occupied)
    ref.writeBinary(str(tmp_path / "ref.bt"))
    assert (tmp_path / "ref.bt").read_bytes() == (tmp_path / "ours.bt").read_bytes()
    back = earcore.OcTree.read_binary(tmp_path / "ref.bt")
    assert back.size() == ref.size()
    assert np.array_equal(back.is_occupied(centres).astype(bool), occupied)
    # Loaded values are the clamping bounds, as in OctoMap.
    lo, hi = np.log(0.1192 / 0.8808), np.log(0.971 / 0.029)
    values = back.log_odds(centres)
    assert np.allclose(np.where(occupied, hi, lo), values, atol=1e-5)


def test_bt_of_octomap_tree_equals_ours(octomap, tmp_path, scan):
    ref = octomap.OcTree(0.05)
    for pts, origin in scan:
        ref.insertPointCloud(pts, origin)
    ours = build(scan)
    ours.write_binary(tmp_path / "ours.bt")
    assert ref.writeBinary() == (tmp_path / "ours.bt").read_bytes()


def test_empty_tree_files(octomap, tmp_path):
    tree = earcore.OcTree(0.05)
    tree.write(tmp_path / "e.ot")
    tree.write_binary(tmp_path / "e.bt")
    assert earcore.OcTree.read(tmp_path / "e.ot").size() == 0
    assert earcore.OcTree.read_binary(tmp_path / "e.bt").size() == 0
    ref = octomap.OcTree(0.05)
    assert ref.readBinary(str(tmp_path / "e.bt"))


def test_missing_file_is_an_os_error(tmp_path):
    with pytest.raises(OSError, match="cannot read"):
        earcore.OcTree.read_binary(tmp_path / "nope.bt")


def test_write_to_bad_path_keeps_nothing_half_written(tmp_path):
    tree = build(scene_scans(1, n_views=1))
    with pytest.raises(OSError):
        tree.write_binary(tmp_path / "no-such-dir" / "x.bt")
    good = tmp_path / "good.bt"
    tree.write_binary(good)
    before = good.read_bytes()
    tree.write_binary(good)  # rewriting goes through a temporary file and a rename
    assert good.read_bytes() == before
    assert not list(tmp_path.glob("*.earcore-tmp"))


@pytest.fixture(scope="module")
def sample_files(tmp_path_factory, scan):
    d = tmp_path_factory.mktemp("files")
    tree = build(scan[:1], 0.1)
    tree.write(d / "s.ot")
    tree.write_binary(d / "s.bt")
    return {"ot": (d / "s.ot").read_bytes(), "bt": (d / "s.bt").read_bytes()}


def load(kind: str, data: bytes, tmp_path):
    path = tmp_path / f"x.{kind}"
    path.write_bytes(data)
    return (earcore.OcTree.read if kind == "ot" else earcore.OcTree.read_binary)(path)


@pytest.mark.parametrize("kind", ["ot", "bt"])
def test_every_truncation_raises(sample_files, tmp_path, kind):
    data = sample_files[kind]
    header_end = data.index(b"data\n") + 5
    cuts = sorted(set(range(0, header_end + 40)) | set(range(header_end, len(data), max(1, len(data) // 200))))
    for cut in cuts:
        with pytest.raises(earcore.MapFormatError):
            load(kind, data[:cut], tmp_path)


@pytest.mark.parametrize("kind", ["ot", "bt"])
def test_header_damage_raises(sample_files, tmp_path, kind):
    data = sample_files[kind]
    for old, new in [(b"res 0.1", b"res -0.1"), (b"res 0.1", b"res nan"), (b"id OcTree", b""), (b"size", b"sixe")]:
        with pytest.raises(earcore.MapFormatError):
            load(kind, data.replace(old, new, 1), tmp_path)
    with pytest.raises(earcore.MapFormatError):
        load(kind, b"\x89PNG\r\n\x1a\n" + data, tmp_path)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["ot", "bt"]), flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=8))
@example(kind="bt", flips=[(0.42578125, 170)])  # loads with eight equal children
def test_corrupted_bytes_load_or_raise_never_crash(sample_files, tmp_path, kind, flips):
    data = bytearray(sample_files[kind])
    for where, value in flips:
        data[min(int(where * len(data)), len(data) - 1)] = value
    try:
        tree = load(kind, bytes(data), tmp_path)
    except earcore.MapFormatError:
        return  # refused, with the library's error
    # Loaded: damage that still parses must give a whole tree, one that writes and reads back
    # to the same map. (Not always the same leaves: damage can leave eight equal children,
    # which writing prunes into their parent, as OctoMap does.)
    path = tmp_path / f"again.{kind}"
    (tree.write if kind == "ot" else tree.write_binary)(path)
    again = (earcore.OcTree.read if kind == "ot" else earcore.OcTree.read_binary)(path)
    centres, _, _ = tree.leaves()
    np.testing.assert_array_equal(again.log_odds(centres), tree.log_odds(centres))
    assert again.num_leaf_nodes() <= tree.num_leaf_nodes()


def test_writing_through_a_link_keeps_the_link_and_the_files_mode(tmp_path):
    """A map written to a symbolic link lands in the link's target (the link stays),
    an existing file keeps its permissions, and a device is written, not replaced."""
    import os
    import stat

    tree = earcore.OcTree(0.1)
    tree.insert_point_cloud(np.array([[0.3, 0.2, 0.1]]), [0.0, 0.0, 0.0])
    target = tmp_path / "real.bt"
    target.write_bytes(b"old")
    os.chmod(target, 0o600)
    link = tmp_path / "link.bt"
    link.symlink_to(target)
    tree.write_binary(link)
    assert link.is_symlink() and stat.S_IMODE(target.stat().st_mode) == 0o600
    assert earcore.OcTree.read_binary(target).size() == tree.size()
    assert not list(tmp_path.glob("*.earcore-tmp"))
    # A link to a file not written yet (latest -> today's): the file is created, the link stays.
    (tmp_path / "maps").mkdir()
    latest = tmp_path / "latest.bt"
    latest.symlink_to("maps/today.bt")
    tree.write_binary(latest)
    assert latest.is_symlink() and earcore.OcTree.read_binary(tmp_path / "maps" / "today.bt").size() == tree.size()
    if os.path.exists("/dev/full"):
        with pytest.raises(OSError):
            tree.write_binary("/dev/full")  # a full device: an error, and the device stays
        assert stat.S_ISCHR(os.stat("/dev/full").st_mode)
