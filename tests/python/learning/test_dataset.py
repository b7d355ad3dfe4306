"""The torch dataset over a generated shard: every item against the CSV read with the
csv module, the noise's determinism, and clear errors for damaged datasets."""

from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("pybullet")

sys.path.insert(0, str(Path(__file__).parent))
from format_folder import write_folder  # noqa: E402

from earcore.learning.dataset import ImageDataset  # noqa: E402
from earcore.learning.errors import DatasetError  # noqa: E402
from earcore.learning.shards import write_manifest  # noqa: E402
from earcore.sim.robot_images import RobotImageOptions, generate_shard, manifest_for, plan_shards  # noqa: E402
from earcore.transforms import quaternion  # noqa: E402


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("robots")
    options = RobotImageOptions(robots=("ur3", "panda"), mode="random", count=6, shard_size=6, person=0.5)
    shards = plan_shards(options)
    write_manifest(out, manifest_for(options, shards))
    for i in range(len(shards)):
        generate_shard(options, i, out)
    return out


def copy(folder, tmp_path):
    target = tmp_path / "copy"
    shutil.copytree(folder, target)
    return target


def test_items_are_the_csv_labels(folder):
    data = ImageDataset(folder, split=None, noise=False)
    assert len(data) == 12 and data.robots == ["ur3", "panda"] and data.num_keypoints == 8 and data.image_size == (128, 106)
    rows = [r for name in ("shard-00000", "shard-00001") for r in csv.DictReader(open(folder / f"{name}.csv"))]
    import tarfile

    import cv2

    for i, row in enumerate(rows):
        item = data[i]
        robot = data.robots.index(row["robot"])
        assert int(item["robot"]) == robot == int(row["robot_class"])
        count = 7 if row["robot"] == "ur3" else 8
        assert item["keypoint_valid"].tolist() == [k < count for k in range(8)]
        for k in range(count):
            assert np.allclose(item["keypoints"][k].numpy(), [float(row[f"kp{k}_{c}"]) for c in "xyz"], atol=1e-6)
            assert np.allclose(item["pixels"][k].numpy(), [float(row[f"kp{k}_{c}"]) for c in "uv"], atol=1e-4)
            assert bool(item["keypoint_in_image"][k]) == (row[f"kp{k}_in_image"] == "1")
        if count < 8:
            assert row["kp7_x"] == "" and item["keypoints"][7].abs().sum() == 0
        assert np.allclose(item["base"].numpy(), [float(row[c]) for c in ("base_x", "base_y", "base_z")], atol=1e-6)
        q = quaternion(item["base_rotation"].double().numpy())  # (x, y, z, w)
        expected = [float(row[c]) for c in ("base_qx", "base_qy", "base_qz", "base_qw")]
        assert min(np.abs(np.subtract(q, expected)).max(), np.abs(np.add(q, expected)).max()) < 1e-5
        K = item["intrinsics"].numpy()
        assert np.allclose([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], [float(row[c]) for c in ("fx", "fy", "cx", "cy")], atol=1e-4)
        dof = 6 if row["robot"] == "ur3" else 9
        assert np.allclose(item["joints"][:dof].numpy(), [float(row[f"q{j}"]) for j in range(dof)], atol=1e-6)
        # The image and the links from the tar, decoded by OpenCV.
        shard = "shard-00000" if i < 6 else "shard-00001"
        with tarfile.open(folder / f"{shard}.tar") as tar:
            rgb = cv2.imdecode(np.frombuffer(tar.extractfile(f"{row['key']}.rgb.png").read(), np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
            links = cv2.imdecode(np.frombuffer(tar.extractfile(f"{row['key']}.links.png").read(), np.uint8), cv2.IMREAD_UNCHANGED)
        assert np.allclose(item["image"].numpy().transpose(1, 2, 0) * 255, rgb, atol=1e-3)
        assert np.array_equal(item["links"].numpy(), links)
        assert np.array_equal(item["mask"][0].numpy(), (links > 0).astype(np.float32))
        assert abs(float(item["mask"].mean()) - float(row["coverage"])) < 1e-6


def test_splits_and_robot_subsets(folder):
    train, test = ImageDataset(folder, "train", noise=False), ImageDataset(folder, "test", noise=False)
    assert len(train) + len(test) == 12
    assert {int(train[i]["robot"]) for i in range(len(train))} <= {0, 1}
    only = ImageDataset(folder, None, robots=["panda"], noise=False)
    assert len(only) == 6 and all(int(only[i]["robot"]) == 1 for i in range(6))
    with pytest.raises(ValueError, match="iiwa"):
        ImageDataset(folder, robots=["iiwa"])
    with pytest.raises(ValueError, match="split"):
        ImageDataset(folder, split="val")


def test_noise_is_deterministic_per_seed_epoch_and_index(folder):
    clean = ImageDataset(folder, None, noise=False)[2]["image"]
    a, b = ImageDataset(folder, None, seed=3), ImageDataset(folder, None, seed=3)
    first = a[2]["image"]
    assert torch.equal(first, b[2]["image"])
    assert not torch.equal(first, clean) and float((first - clean).abs().mean()) < 0.15
    assert first.min() >= 0 and first.max() <= 1
    a.set_epoch(1)
    assert not torch.equal(a[2]["image"], first)
    a.set_epoch(0)
    assert torch.equal(a[2]["image"], first)
    assert not torch.equal(ImageDataset(folder, None, seed=4)[2]["image"], first)


def test_damaged_datasets_name_the_file(folder, tmp_path):
    bad = copy(folder, tmp_path)
    tar = bad / "shard-00001.tar"
    tar.write_bytes(tar.read_bytes()[:3000])
    with pytest.raises(DatasetError, match="shard-00001.tar"):
        len(ImageDataset(bad, None))
    shutil.rmtree(bad)
    bad = copy(folder, tmp_path)
    path = bad / "shard-00000.csv"
    rows = list(csv.reader(open(path)))
    drop = rows[0].index("kp2_v")
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([r[:drop] + r[drop + 1 :] for r in rows])
    with pytest.raises(DatasetError, match="shard-00000.csv.*'kp2_v'"):
        len(ImageDataset(bad, None))
    shutil.rmtree(bad)
    bad = copy(folder, tmp_path)
    path = bad / "shard-00000.csv"
    rows = list(csv.reader(open(path)))
    rows[2][rows[0].index("base_y")] = ""
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    with pytest.raises(DatasetError, match="shard-00000.csv: row 3 lacks the base pose"):
        len(ImageDataset(bad, None))
    shutil.rmtree(bad)
    bad = copy(folder, tmp_path)
    manifest = json.loads((bad / "manifest.json").read_text())
    manifest["version"] = 7
    (bad / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="manifest.json: format version 7"):
        ImageDataset(bad)
    with pytest.raises(DatasetError, match="no such dataset folder"):
        ImageDataset(tmp_path / "nowhere")


def test_quaternions_scalar_first_give_back_the_rotations_they_came_from():
    """The dataset's base rotations (CSV: w, x, y, z) against the matrices `quaternion`
    was computed from, and against Rodrigues' formula for a hand-made quaternion."""
    from earcore.transforms import quaternion, rotation_from_quaternion, rotation_from_vector

    rng = np.random.default_rng(2)
    rotations = [rotation_from_vector(v) for v in rng.normal(0, 1.5, (20, 3))]
    wxyz = np.array([(w, x, y, z) for x, y, z, w in (quaternion(r) for r in rotations)])
    assert np.allclose(rotation_from_quaternion(wxyz), np.array(rotations), atol=1e-12)
    half = np.radians(30) / 2  # 30° about z
    assert np.allclose(rotation_from_quaternion([np.cos(half), 0, 0, np.sin(half)]), rotation_from_vector([0, 0, np.radians(30)]))


def test_datasets_join_in_order_and_unite_robots_by_name(folder, tmp_path):
    from earcore.learning.dataset import ImageDatasets

    train, test = ImageDataset(folder, split="train", noise=False), ImageDataset(folder, split="test", noise=False)
    both = ImageDatasets([train, test])
    assert len(both) == len(train) + len(test) == 12
    assert both.robots == train.robots and both.image_size == train.image_size and both.num_keypoints == train.num_keypoints
    items = [train[i] for i in range(len(train))] + [test[i] for i in range(len(test))]
    for i, want in enumerate(items):
        got = both[i]
        assert torch.equal(got["image"], want["image"]) and torch.equal(got["keypoints"], want["keypoints"])
    assert torch.equal(both[-1]["image"], items[-1]["image"])
    with pytest.raises(IndexError):
        both[12]
    # The epoch reaches every part: noisy parts draw new noise together.
    noisy = ImageDatasets([ImageDataset(folder, split="train", noise=True), ImageDataset(folder, split="test", noise=True)])
    first = noisy[len(train)]["image"].clone()
    noisy.set_epoch(1)
    assert not torch.equal(noisy[len(train)]["image"], first)
    # Other robots are united by name; their keypoints and joints padded and marked invalid.
    w, h = train.image_size
    iiwa = write_folder(tmp_path / "iiwa", robots=("iiwa", "ur3"), per_robot=2, width=w, height=h, seed=3)
    other = ImageDataset(iiwa, split=None, noise=False)
    united = ImageDatasets([train, other])
    assert united.robots == [*train.robots, "iiwa"] and united.num_keypoints == max(train.num_keypoints, other.num_keypoints)
    labels = united.robot_labels()
    for i in range(len(other)):
        got, want = united[len(train) + i], other[i]
        name = other.robots[int(want["robot"])]
        assert united.robots[int(got["robot"])] == name and int(labels[len(train) + i]) == int(got["robot"])
        k = want["keypoints"].shape[0]
        assert torch.equal(got["keypoints"][:k], want["keypoints"]) and not got["keypoint_valid"][k:].any()
    short = ImageDatasets([other, train])  # fewer keypoints joining more: padded
    item = short[len(other)]
    assert item["keypoints"].shape[0] == short.num_keypoints and not item["keypoint_valid"][train.num_keypoints :].any()
    assert set(united.manifest["keypoints"]) == set(united.robots)
    small = write_folder(tmp_path / "small", robots=("ur3",), per_robot=2, width=16, height=12)
    with pytest.raises(DatasetError, match="image size"):
        ImageDatasets([train, ImageDataset(small, split=None)])
    with pytest.raises(ValueError):
        ImageDatasets([])
