"""One-shot segmentation (AAMAS 2019): needle crops, the held-out protocol's pairs and
trials against the labels, the classification metric on hand-made masks, the gating,
and a tiny segmenter overfitting one batch."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from earcore.learning.losses import soft_iou_error
from earcore.learning.train import collate
from earcore.parts.oneshot import build_oneshot
from earcore.parts.oneshot_data import needle_crop, split_classes
from earcore.parts.oneshot_evaluate import score_trials

pytest.importorskip("pybullet")


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    from earcore.app.parts import main

    root = tmp_path_factory.mktemp("oneshot")
    common = ["--size", "64x48", "--workers", "1", "--quiet"]
    assert main(["generate", "--out", str(root / "hay"), "--count", "40", "--objects", "2-5", "--seed", "5", *common]) == 0
    assert main(["generate", "--out", str(root / "needles"), "--count", "60", "--objects", "1-1", "--seed", "6", *common]) == 0
    return root / "hay", root / "needles"


def test_needle_crop_is_the_square_around_the_part():
    image = torch.zeros(3, 48, 64)
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:34] = True  # 10 rows x 4 columns
    image[0][torch.from_numpy(mask)] = 1.0
    crop, crop_mask = needle_crop(image, mask, size=16, margin=0.3)
    # side 10 * 1.6 = 16 px around the centre (row 15, column 32): the crop is 1:1
    assert crop.shape == (3, 16, 16) and crop_mask.shape == (1, 16, 16)
    assert torch.equal(crop_mask[0] > 0, torch.from_numpy(mask[7:23, 24:40]))
    assert torch.allclose(crop[0], image[0, 7:23, 24:40])
    # at the image's edge the square moves inside
    edge = np.zeros((48, 64), bool)
    edge[0:4, 60:64] = True
    _, m = needle_crop(torch.zeros(3, 48, 64), edge, size=8, margin=0.5)
    assert int(m.sum()) == 16  # 4 x 4 part in an 8 x 8 window, 1:1
    with pytest.raises(Exception, match="no part"):
        needle_crop(image, np.zeros((48, 64), bool))


def test_needle_crops_keep_the_cameras_scale():
    from earcore.parts.oneshot_data import needle_size

    image = torch.rand(3, 48, 64)
    small = np.zeros((48, 64), bool)
    small[20:24, 30:33] = True  # 4 x 3 px: a 16 px window around it, not magnified
    crop, m = needle_crop(image, small, size=16)
    assert int(m.sum()) == 12 and torch.equal(crop, image[:, 14:30, 23:39])
    big = np.zeros((48, 64), bool)
    big[4:44, 10:14] = True  # 40 rows: 60 px with the margins, clipped to the image's 48, shrunk to 16
    crop, m = needle_crop(image, big, size=16)
    assert crop.shape == (3, 16, 16) and 0 < int(m.sum()) < 40 * 4
    assert torch.allclose(crop.mean((1, 2)), image[:, :, 8:56].mean((1, 2)), atol=0.05)  # an average of the window
    assert [needle_size(w) for w in (64, 128, 256, 640)] == [16, 32, 64, 160]
    assert [needle_size(w, divisor=16) for w in (64, 160, 192)] == [16, 32, 48]  # multiples of the segmenter's divisor


def test_options_and_older_checkpoints(tmp_path):
    from earcore.errors import ConfigError
    from earcore.learning.checkpoint import Checkpoint, save_checkpoint
    from earcore.parts.oneshot_train import NETWORK, load_oneshot

    with pytest.raises(ConfigError, match="true or false"):
        build_oneshot(match="False")
    with pytest.raises(ConfigError, match="pooling"):
        build_oneshot(pooling="max")
    # a checkpoint written before pooling / sharpen / match: the paper's gating, power 1
    torch.manual_seed(1)
    old = build_oneshot(in_channels=3, widths=(8, 8, 8), dropout=0.0, pooling="image", sharpen=False, match=False).eval()
    weights = {k: v for k, v in old.state_dict().items() if k != "log_sharpness"}
    options = {k: v for k, v in old.options.to_dict().items() if k not in ("pooling", "sharpen", "match")}
    save_checkpoint(tmp_path / "checkpoint.pt", Checkpoint(step=1, seconds=0.0, model=weights, meta={"network": NETWORK, "options": options}))
    loaded, _ = load_oneshot(tmp_path)
    needle, haystack = torch.rand(1, 3, 16, 16), torch.rand(1, 3, 24, 32)
    with torch.no_grad():
        assert torch.allclose(loaded.segment(needle, haystack), old.segment(needle, haystack))


def test_split_classes():
    names = ["a", "b", "c", "d"]
    assert split_classes(names, ["d", "b"]) == ([0, 2], [1, 3])
    with pytest.raises(ValueError, match="unknown"):
        split_classes(names, ["x"])
    with pytest.raises(ValueError, match="distinct"):
        split_classes(names, ["a", "a"])


def test_pairs_and_trials_follow_the_protocol(folders):
    from earcore.parts.dataset import PartImages
    from earcore.parts.oneshot_data import HeldOutTrials, OneShotPairs, visible_pixels

    hay, needles = folders
    hay_all = PartImages(hay, split=None, noise=False)
    counts = visible_pixels(hay_all)
    a = hay_all._load()
    # brute force: pixels per type from the instance layer and the labels
    for k in range(len(counts)):
        for c in range(13):
            slots = [i for i in range(int(a["count"][k])) if a["classes"][k, i] == c]
            assert counts[k, c] == sum(int((a["instances"][k] == i + 1).sum()) for i in slots)
    present = (counts >= 12).any(0)
    held = [int(c) for c in np.argsort(-(counts >= 12).sum(0))[:2]]  # the two most common types
    assert present[held].all()
    seen = [c for c in range(13) if c not in held]
    pairs = OneShotPairs(hay_all, PartImages(needles, split=None, noise=False), seen, depth=False)
    for k in range(len(pairs)):
        item = pairs[k]
        image = int(pairs.images[k])
        assert not np.isin(a["classes"][image], held).any()  # never a held-out part in training
        cls = int(item["cls"])
        assert cls not in held and counts[image, cls] >= 12 and cls in pairs.by_class
        assert item["haystack"].shape == (3, 48, 64) and item["needle"].shape == (3, 16, 16)
        assert int(item["target"].sum()) == counts[image, cls]  # flips keep the pixels
        assert int(item["all"].sum()) == int((a["instances"][image] > 0).sum())
        assert item["needle_mask"].sum() > 0
    trials = HeldOutTrials(hay_all, PartImages(needles, split=None, noise=False), held)
    assert len(trials) == 2 * int(((counts[:, held] >= 12).all(1)).sum())
    for k in range(len(trials)):
        image, cls, needle = trials.trials[k]
        assert cls in held and (counts[image, held] >= 12).all()
        item = trials[k]
        assert int(item["valid"].sum()) == int((a["classes"][image] == cls).sum())
        assert torch.equal(item["target"][0], item["masks"][cls])


def _needle_types(needles):
    from earcore.parts.dataset import PartImages
    from earcore.parts.oneshot_data import visible_pixels

    n = PartImages(needles, split=None, noise=False)
    a = n._load()
    ok = visible_pixels(n).sum(1) >= 12
    return set(int(c) for c in a["classes"][ok, 0])


def test_classification_metric_on_hand_made_masks():
    masks = torch.zeros(4, 3, 4, 4)
    masks[:, 0, :2, :2] = 1  # type 0: top left
    masks[:, 1, 2:, 2:] = 1  # type 1: bottom right
    belief = torch.zeros(4, 1, 4, 4)
    belief[0, 0, :2, :2] = 0.9  # exactly type 0
    belief[1, 0, 2:, 2:] = 0.9  # type 1, asked for type 0
    belief[2, 0, :2, :2] = 0.9  # both halves: a tie
    belief[2, 0, 2:, 2:] = 0.9
    belief[3, 0, 0, 0] = 0.9  # one pixel of type 0: IoU 1/4
    batch = {
        "masks": masks,
        "cls": torch.tensor([0, 0, 0, 0]),
        "points": torch.tensor([[[0.5, 0.5]]] * 4),
        "valid": torch.ones(4, 1, dtype=torch.bool),
        "depth": torch.full((4, 1), 0.4),
        "intrinsics": torch.tensor([[100.0, 100.0, 2.0, 2.0]] * 4),
    }
    r = score_trials(belief, batch)
    assert r.chosen == [0, 1, -1, 0]
    assert r.accuracy == pytest.approx(0.5)
    assert r.iou == pytest.approx([1.0, 0.0, 0.5, 0.25])
    # the correct trials' pickup: trial 0's centroid is (0.5, 0.5), on the point (error 0); trial 3's
    # is (0, 0): 0.707 px at 0.4 m and f = 100 px = 0.283 cm, Eq. 4 gives d²/(d²+1)
    d = 100 * 0.4 * np.sqrt(0.5) / 100
    assert r.pickup_errors == pytest.approx([0.0, d**2 / (d**2 + 1)], abs=1e-4)


def test_gates_switch_filters_by_the_needle():
    torch.manual_seed(0)
    net = build_oneshot(in_channels=3, widths=(8, 8, 8), dropout=0.0).eval()
    needle = torch.rand(2, 3, 16, 16)
    mask = torch.zeros(2, 1, 16, 16)
    mask[0, 0, 4:8, 4:12] = 1
    mask[1, 0, 10:16, 0:6] = 1
    gates, vector = net.needle_gates(needle, mask)
    assert [g.shape for g in gates] == [(2, 8)] * 3 and vector.shape == (2, 8)
    for g in gates:
        assert torch.allclose(g.mean(1), torch.ones(2), atol=1e-4)  # a stack keeps its scale
    # by hand: stack 1's responses are its positive outputs averaged over the part's pixels,
    # stack 2's (half the resolution) over the mask's share of each cell; at power 1 the gates are their ratios to the mean
    features = net.encode(needle)
    r1 = (features[0].clamp(min=0) * mask).sum((2, 3)) / mask.sum((2, 3))
    assert torch.allclose(gates[0], r1 / r1.mean(1, keepdim=True), atol=1e-4)
    share = mask.reshape(2, 1, 8, 2, 8, 2).mean((3, 5))
    r2 = (features[1].clamp(min=0) * share).sum((2, 3)) / share.sum((2, 3))
    assert torch.allclose(gates[1], r2 / r2.mean(1, keepdim=True), atol=1e-4)
    # a learned power p sharpens: gates = r^p / mean(r^p)
    with torch.no_grad():
        net.log_sharpness[0] = float(np.log(3.0))
    sharp, _ = net.needle_gates(needle, mask)
    assert torch.allclose(sharp[0], r1**3 / (r1**3).mean(1, keepdim=True), atol=1e-3)
    assert float(sharp[0].detach().std()) > float(gates[0].detach().std())
    with pytest.raises(ValueError, match="part mask"):
        net.needle_gates(needle)
    with pytest.raises(ValueError, match="empty"):
        net.needle_gates(needle, torch.zeros(2, 1, 16, 16))
    # the paper's pooling averages over the whole needle image
    image_pooled = build_oneshot(in_channels=3, widths=(8, 8, 8), dropout=0.0, pooling="image").eval()
    image_pooled.load_state_dict(net.state_dict())
    g, _ = image_pooled.needle_gates(needle)
    r = image_pooled.encode(needle)[0].clamp(min=0).mean((2, 3)) ** 3
    assert torch.allclose(g[0], r / r.mean(1, keepdim=True), atol=1e-3)
    gates = sharp
    # the similarity maps: at a haystack cell, the cosine of its gated features and the needle part's mean features, gated
    haystack = torch.rand(2, 3, 24, 32)
    gated = net.encode(haystack, gates)
    share = mask.reshape(2, 1, 4, 4, 4, 4).mean((3, 5))
    prototype = (features[2] * share).sum((2, 3)) / share.sum((2, 3))
    (_, prototypes), _ = net._needle(needle, mask)
    assert torch.allclose(prototypes[2], prototype, atol=1e-5)
    maps = [m.detach() for m in net.similarity(gated, [p * g for p, g in zip(prototypes, gates)])]
    a, b = gated[2][1, :, 3, 5].detach(), (prototype[1] * gates[2][1]).detach()
    assert maps[2].shape == (2, 1, 6, 8)
    assert float(maps[2][1, 0, 3, 5]) == pytest.approx(float(a @ b / (a.norm() * b.norm())), abs=1e-5)
    # gating by hand: the gated encoder equals the plain one's stacks times the gates, stack by stack
    plain = net.stacks[0](haystack)
    gated = net.encode(haystack, gates)
    assert torch.allclose(gated[0], plain * gates[0][:, :, None, None], atol=1e-5)
    # different needles give different beliefs on the same haystack
    other = torch.rand(2, 3, 16, 16) * torch.tensor([1.0, 0.0, 0.0])[:, None, None]
    assert not torch.allclose(net.segment(needle, haystack, mask), net.segment(other, haystack, mask))
    with pytest.raises(ValueError, match="multiples"):
        net.segment(needle, torch.rand(1, 3, 25, 32), mask)


def test_a_tiny_segmenter_overfits_one_batch(folders):
    from earcore.parts.dataset import PartImages
    from earcore.parts.oneshot import TASKS
    from earcore.parts.oneshot_data import OneShotPairs
    from earcore.parts.oneshot_train import OneShotObjective

    hay, needles = folders
    seen = sorted(_needle_types(needles))
    pairs = OneShotPairs(PartImages(hay, split=None, noise=False), PartImages(needles, split=None, noise=False), seen, depth=False)
    batch = collate([pairs[k] for k in range(4)])
    torch.manual_seed(0)
    net = build_oneshot(in_channels=3, widths=(8, 16, 16, 16), dropout=0.0)
    objective = OneShotObjective(TASKS)
    optimiser = torch.optim.Adam(net.parameters(), lr=1e-2)
    first = None
    for _ in range(150):
        losses = objective.losses(batch, net(*objective.inputs(batch)))
        if first is None:
            first = {k: float(v.detach()) for k, v in losses.items()}
        optimiser.zero_grad()
        sum(losses.values()).backward()
        optimiser.step()
    net.eval()
    with torch.no_grad():
        last = {k: float(v) for k, v in objective.losses(batch, net(*objective.inputs(batch))).items()}
        belief = net.segment(batch["needle"], batch["haystack"], batch["needle_mask"])
    assert first["needle"] > 0.8 and last["needle"] < 0.35
    assert last["all"] < 0.35 and last["self"] < 0.35
    assert last["spread"] < first["spread"]
    assert float(soft_iou_error((belief > 0.5).float(), batch["target"])) < 0.4


def test_oneshot_train_command(folders, tmp_path, capsys):
    from earcore.app.parts import main

    hay, needles = folders
    types = sorted(_needle_types(needles))
    from earcore.parts.catalogue import part_names

    names = part_names()
    # hold out two types some haystack shows together (the command needs trials)
    from earcore.parts.dataset import PartImages
    from earcore.parts.oneshot_data import visible_pixels

    seen_together = visible_pixels(PartImages(hay, split="test", noise=False)) >= 12
    pair = next((a, b) for a in types for b in types if a < b and (seen_together[:, a] & seen_together[:, b]).any())
    out = tmp_path / "run"
    args = ["oneshot-train", "--haystacks", str(hay), "--needles", str(needles), "--held-out", f"{names[pair[0]]},{names[pair[1]]}"]
    args += ["--out", str(out), "--steps", "4", "--batch", "2", "--eval-steps", "2", "--rgb", "--option", "widths=[8,8,8,8]", "--no-progress"]
    assert main(args) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["trials"] >= 2 and 0.0 <= results["accuracy"] <= 1.0
    assert set(results["classes"]) == {names[pair[0]], names[pair[1]]}
    assert "Precision" in capsys.readouterr().out
    # "show me this part" with the one-shot segmenter: a rendered needle, then one given as PNGs
    from earcore.learning import png

    show = tmp_path / "show"
    assert main(["show", "--model", str(out), "--needle-part", names[pair[0]], "--size", "64x48", "--out", str(show)]) == 0
    summary = json.loads((show / "show.json").read_text())
    assert summary["network"] == "oneshot" and summary["part"] == names[pair[0]]
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[20:30, 25:40] = (200, 60, 30)
    mask = np.zeros((48, 64), np.uint8)
    mask[20:30, 25:40] = 255
    png.write(tmp_path / "n.png", rgb)
    png.write(tmp_path / "m.png", mask)
    given = ["show", "--model", str(out), "--needle", str(tmp_path / "n.png"), "--needle-mask", str(tmp_path / "m.png"), "--size", "64x48"]
    assert main([*given, "--out", str(show)]) == 0
    assert json.loads((show / "show.json").read_text())["part"] is None  # no truth for a part given by image
    png.write(tmp_path / "m.png", np.zeros((48, 64), np.uint8))
    assert main([*given, "--out", str(show)]) == 1  # an empty mask: a clear refusal
    assert main(["show", "--model", str(out), "--part", names[pair[0]]]) == 2
    assert main([*args[:6], "Nope", "--out", str(tmp_path / "bad"), "--steps", "1"]) == 1
