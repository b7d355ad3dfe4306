"""`earcore dataset robots` end to end: worker processes, resuming to the same bytes,
refusing a folder made with other options, and Ray tasks on a local Ray instance."""

from __future__ import annotations

import hashlib
import json

import pytest

pytest.importorskip("pybullet")

from earcore.app.dataset import main  # noqa: E402

TINY = ["robots", "--robots", "ur3,iiwa", "--scale", "0.01", "--shard-size", "4", "--quiet"]


def digest(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    out = tmp_path_factory.mktemp("made") / "robots"
    assert main([*TINY, "--out", str(out), "--workers", "2"]) == 0
    return out


def test_two_workers_write_every_shard(made, capsys):
    manifest = json.loads((made / "manifest.json").read_text())
    # ur3: 2 + 3 + 5 images (1 % of 211, 252, 463); iiwa: 14 recordings of 1.
    assert manifest["generator"]["recordings"] == {"ur3": [2, 3, 5], "iiwa": [1] * 14}
    assert sum(s["samples"] for s in manifest["shards"]) == 24
    assert manifest["robots"] == ["ur3", "iiwa"] and manifest["num_keypoints"] == 8 and manifest["max_dof"] == 7
    for entry in manifest["shards"]:
        lines = (made / f"{entry['name']}.csv").read_text().splitlines()
        assert len(lines) == entry["samples"] + 1
    torch = pytest.importorskip("torch")
    from earcore.learning.dataset import ImageDataset

    data = ImageDataset(made, split=None, noise=False)
    assert len(data) == 24 and isinstance(data[0]["image"], torch.Tensor)


def test_resume_completes_missing_shards_with_identical_bytes(made, tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(made, copy)
    before = digest(copy)
    (copy / "shard-00001.tar").unlink()
    (copy / "shard-00002.csv").unlink()  # interrupted after its tar
    assert main([*TINY, "--out", str(copy), "--workers", "1"]) == 0
    out = capsys.readouterr().out
    sizes = [s["samples"] for s in json.loads((copy / "manifest.json").read_text())["shards"]]
    assert out.startswith(f"{sizes[1] + sizes[2]} images in") and f"{24 - sizes[1] - sizes[2]} already there" in out
    assert digest(copy) == before


def test_other_options_are_refused(made, capsys):
    assert main([*TINY, "--out", str(made), "--seed", "3"]) == 2
    err = capsys.readouterr().err
    assert "other options (seed differ)" in err and str(made) in err
    assert main(["robots", "--out", str(made.parent / "x"), "--robots", "ur3,r2d2", "--quiet"]) == 2
    assert "unknown robot 'r2d2'" in capsys.readouterr().err
    (made.parent / "junk").mkdir()
    (made.parent / "junk" / "notes.txt").write_text("mine")
    assert main([*TINY, "--out", str(made.parent / "junk")]) == 2
    assert "not a dataset folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*TINY, "--out", str(made), "--size", "128by106"])


def test_ray_tasks_write_the_same_dataset(made, tmp_path):
    ray = pytest.importorskip("ray")
    out = tmp_path / "ray"
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        assert main([*TINY, "--out", str(out), "--ray"]) == 0
    finally:
        ray.shutdown()
    assert digest(out) == digest(made)
