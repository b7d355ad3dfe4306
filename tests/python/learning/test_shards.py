"""The "earcore-images" shards: what is written is what a plain tar/CSV reader finds,
and what `read_shard` returns; damaged shards and manifests give errors naming the file."""

from __future__ import annotations

import csv
import io
import json
import tarfile

import numpy as np
import pytest

from earcore.learning import png
from earcore.learning.errors import DatasetError
from earcore.learning.shards import (
    Sample,
    columns,
    complete_shards,
    read_manifest,
    read_shard,
    write_manifest,
    write_shard,
)

W, H = 12, 10


def samples(n=3):
    rng = np.random.default_rng(1)
    out = []
    for i in range(n):
        row = {"robot": "ur5", "recording": i, "split": "train", "fx": 10.5 + i, "q0": -0.25 * i, "kp0_u": None}
        out.append(Sample(f"s{i}", {"rgb": rng.integers(0, 256, (H, W, 3), dtype=np.uint8), "links": rng.integers(0, 9, (H, W), dtype=np.uint8)}, row))
    return out


def test_a_shard_reads_back_and_opens_with_plain_tools(tmp_path):
    header = columns(2, 1)
    assert header[:5] == ["key", "robot", "robot_class", "recording", "split"]
    assert header[-8:] == ["base_x", "base_y", "base_z", "base_qw", "base_qx", "base_qy", "base_qz", "coverage"]
    assert "kp0_in_image" in header and "q1" in header and "kp1_x" not in header
    written = samples()
    write_shard(tmp_path, "shard-00000", written, header)
    # Plain tools: tarfile, csv and OpenCV (an independent PNG decoder).
    cv2 = pytest.importorskip("cv2")
    with tarfile.open(tmp_path / "shard-00000.tar") as tar:
        names = tar.getnames()
        assert names == [f"s{i}.{k}.png" for i in range(3) for k in ("rgb", "links")]
        data = tar.extractfile("s1.rgb.png").read()
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1], written[1].images["rgb"])
    rows = list(csv.DictReader(open(tmp_path / "shard-00000.csv")))
    assert [r["key"] for r in rows] == ["s0", "s1", "s2"]
    assert float(rows[2]["q0"]) == -0.5 and rows[2]["kp0_u"] == "" and rows[1]["fx"] == "11.5"
    shard = read_shard(tmp_path, "shard-00000", W, H, required=["fx"])
    assert np.array_equal(shard.images["rgb"], np.stack([s.images["rgb"] for s in written]))
    assert np.array_equal(shard.images["links"], np.stack([s.images["links"] for s in written]))
    assert np.isnan(shard.numbers("kp0_u")).all()
    assert complete_shards(tmp_path) == {"shard-00000"}


def test_incomplete_shards_are_not_complete(tmp_path):
    write_shard(tmp_path, "shard-00000", samples(1), columns(1, 1))
    write_shard(tmp_path, "shard-00001", samples(1), columns(1, 1))
    (tmp_path / "shard-00001.csv").unlink()  # interrupted before its CSV
    (tmp_path / ".shard-00002.tar.tmp-1").write_bytes(b"partial")
    assert complete_shards(tmp_path) == {"shard-00000"}


def test_shards_cut_short_are_not_complete_for_their_manifest(tmp_path):
    """A shard whose files exist but were cut short (a truncated copy, a full disk) is
    generated again on resuming: it was counted as done, and training then refused the
    folder as damaged."""
    header = columns(2, 1)
    for i in range(4):
        write_shard(tmp_path, f"shard-{i:05d}", samples(3), header)
    manifest = {"shards": [{"name": f"shard-{i:05d}", "samples": 3} for i in range(4)]}
    assert complete_shards(tmp_path, manifest) == {f"shard-{i:05d}" for i in range(4)}
    tar = tmp_path / "shard-00001.tar"
    data = tar.read_bytes()
    tar.write_bytes(data[:4000])  # the last images' bytes gone (the images end near 5.8 kB)
    rows = tmp_path / "shard-00002.csv"
    rows.write_text("".join(rows.read_text().splitlines(keepends=True)[:-1]))  # a row gone
    (tmp_path / "shard-00003.tar").write_bytes(b"")
    assert complete_shards(tmp_path, manifest) == {"shard-00000"}
    for name in ("shard-00001", "shard-00002", "shard-00003"):
        with pytest.raises(DatasetError):
            read_shard(tmp_path, name, W, H, samples=3)


def test_damage_is_reported_with_the_file(tmp_path):
    write_shard(tmp_path, "shard-00000", samples(), columns(2, 1))
    tar = tmp_path / "shard-00000.tar"
    good = tar.read_bytes()
    tar.write_bytes(good[:700])
    with pytest.raises(DatasetError, match="shard-00000.tar"):
        read_shard(tmp_path, "shard-00000", W, H)
    tar.write_bytes(good)
    with pytest.raises(DatasetError, match="shard-00000.tar.*expected \\(20, 12, 3\\)"):
        read_shard(tmp_path, "shard-00000", 12, 20)
    with pytest.raises(DatasetError, match="shard-00000.csv.*missing column 'kp3_x'"):
        read_shard(tmp_path, "shard-00000", W, H, required=["kp3_x"])
    # A CSV row whose images are not in the tar.
    text = (tmp_path / "shard-00000.csv").read_text().replace("\ns2,", "\nzz,")
    (tmp_path / "shard-00000.csv").write_text(text)
    with pytest.raises(DatasetError, match="no zz.rgb.png"):
        read_shard(tmp_path, "shard-00000", W, H)
    # An image whose bytes were damaged inside the tar.
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as out:
        data = bytearray(png.encode(samples(1)[0].images["rgb"]))
        data[-20] ^= 0x55
        info = tarfile.TarInfo("s0.rgb.png")
        info.size = len(data)
        out.addfile(info, io.BytesIO(bytes(data)))
    tar.write_bytes(buffer.getvalue())
    with pytest.raises(DatasetError, match="s0.rgb.png"):
        read_shard(tmp_path, "shard-00000", W, H)


def manifest():
    return {
        "format": "earcore-images",
        "version": 1,
        "kind": "robots",
        "width": W,
        "height": H,
        "seed": 0,
        "mode": "random",
        "robots": ["ur5"],
        "keypoints": {"ur5": ["a"]},
        "num_keypoints": 1,
        "links": {"ur5": ["l"]},
        "max_dof": 1,
        "shards": [{"name": "shard-00000", "samples": 3}],
        "generator": {},
    }


def test_manifests_are_checked(tmp_path):
    write_manifest(tmp_path, manifest())
    assert read_manifest(tmp_path) == manifest()
    path = tmp_path / "manifest.json"
    for change, message in (
        ({"version": 2}, "format version 2"),
        ({"format": "webdataset"}, "format 'webdataset'"),
        ({"width": "12"}, "width must be a whole number"),
        ({"shards": [{"name": "x"}]}, "shards must be"),
    ):
        path.write_text(json.dumps({**manifest(), **change}))
        with pytest.raises(DatasetError, match=message):
            read_manifest(tmp_path)
    broken = manifest()
    del broken["links"]
    path.write_text(json.dumps(broken))
    with pytest.raises(DatasetError, match="missing links"):
        read_manifest(tmp_path)
    path.write_text("{not json")
    with pytest.raises(DatasetError, match="manifest.json: not valid JSON"):
        read_manifest(tmp_path)
    with pytest.raises(DatasetError, match="no such dataset folder"):
        read_manifest(tmp_path / "absent")
