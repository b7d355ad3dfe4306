"""`ImageDataset` refuses labels that cannot be labels and damaged manifests and shards
with a `DatasetError` naming the file (and the row and column), instead of training on
them or failing with a KeyError / TypeError / RuntimeWarning:

- "inf" (or "-inf") in a keypoint, the base or a joint angle;
- a focal length of 0 or below;
- a base quaternion of zeros;
- an empty joint angle for a joint the robot has;
- the manifest's `keypoints` without one of its robots, or not a table;
- the manifest's `num_keypoints` smaller than a robot's keypoints;
- a shard whose CSV has fewer (or more) rows than the manifest's `samples`."""

from __future__ import annotations

import csv
import json
import shutil
import sys
import warnings
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

sys.path.insert(0, str(Path(__file__).parent))
from format_folder import write_folder  # noqa: E402

from earcore.learning.dataset import ImageDataset  # noqa: E402
from earcore.learning.errors import DatasetError  # noqa: E402


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return write_folder(tmp_path_factory.mktemp("clean"), robots=("ur3", "ur10"), per_robot=4, width=16, height=16)


def _copy(clean, tmp_path) -> Path:
    target = tmp_path / "copy"
    shutil.copytree(clean, target)
    return target


def _set_cell(folder: Path, column: str, value: str, row: int = 0) -> None:
    path = folder / "shard-00000.csv"
    rows = list(csv.reader(open(path, newline="")))
    rows[row + 1][rows[0].index(column)] = value
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)


def _load(folder: Path) -> ImageDataset:
    data = ImageDataset(folder, split=None, noise=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a NaN made on the way is not an answer either
        len(data)
        data[0]
    return data


@pytest.mark.parametrize(
    "column,value",
    [("kp0_z", "inf"), ("kp2_x", "-inf"), ("base_x", "inf"), ("fx", "0"), ("fy", "-90"), ("q0", ""), ("q5", "inf")],
)
def test_a_nonsense_label_is_a_dataset_error_naming_the_csv(clean, tmp_path, column, value):
    folder = _copy(clean, tmp_path)
    _set_cell(folder, column, value)
    with pytest.raises(DatasetError, match="shard-00000.csv"):
        _load(folder)


def test_a_zero_quaternion_is_a_dataset_error(clean, tmp_path):
    folder = _copy(clean, tmp_path)
    for c in ("base_qw", "base_qx", "base_qy", "base_qz"):
        _set_cell(folder, c, "0")
    with pytest.raises(DatasetError, match="shard-00000.csv"):
        _load(folder)


def _edit_manifest(folder: Path, edit) -> None:
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    "label,edit",
    [
        ("keypoints without a robot", lambda m: m["keypoints"].pop("ur10")),
        ("keypoints a list", lambda m: m.update(keypoints=[])),
        ("fewer keypoints than a robot has", lambda m: m.update(num_keypoints=3)),
    ],
)
def test_a_damaged_manifest_is_a_dataset_error(clean, tmp_path, label, edit):
    folder = _copy(clean, tmp_path)
    _edit_manifest(folder, edit)
    with pytest.raises(DatasetError, match="manifest.json"):
        _load(folder)


@pytest.mark.parametrize("change", ["drop the last row", "repeat the first row"])
def test_a_shard_with_another_row_count_than_the_manifest_is_refused(clean, tmp_path, change):
    folder = _copy(clean, tmp_path)
    path = folder / "shard-00000.csv"
    rows = list(csv.reader(open(path, newline="")))
    rows = rows[:-1] if change == "drop the last row" else rows + [rows[1]]
    with open(path, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows(rows)
    with pytest.raises(DatasetError, match="shard-00000"):
        _load(folder)
