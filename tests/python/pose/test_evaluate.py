"""The results table against an oracle network whose errors are known by construction."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from earcore.pose.evaluate import evaluate

sys.path.insert(0, str(Path(__file__).parent))
from fake_data import FakeDataset  # noqa: E402


class Oracle(torch.nn.Module):
    """Answers from the labels: keypoints shifted by `shift` (m) along x, base by `base_shift`
    along z, the mask with one column of extra pixels, the type right except for index 0."""

    def __init__(self, data, shift, base_shift):
        super().__init__()
        self.data, self.shift, self.base_shift = data, shift, base_shift
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def forward(self, image, mask=None, intrinsics=None):
        # find the samples by their images
        rows = [next(i for i in range(len(self.data)) if torch.equal(self.data[i]["image"], im)) for im in image]
        items = [self.data[i] for i in rows]
        masks = torch.stack([it["mask"] for it in items])
        masks[..., :, 0] = 1.0  # a wrong first column
        kp = torch.stack([it["keypoints"] for it in items]).clone()
        kp[..., 0] += self.shift
        base = torch.stack([it["base"] for it in items]).clone()
        base[:, 2] += self.base_shift
        robot = torch.stack([it["robot"] for it in items]).clone()
        robot[torch.tensor(rows) == 0] = 1 - robot[torch.tensor(rows) == 0]
        return {"mask_logits": masks * 20 - 10, "keypoints": kp, "base": base, "type_logits": torch.nn.functional.one_hot(robot, 2).float()}


def test_table_against_known_errors(tmp_path):
    data = FakeDataset(6, 32, 32, keypoints=4)
    result = evaluate(Oracle(data, 0.05, 0.02), data, "cpu", timing=False)
    truth = torch.stack([data[i]["mask"] for i in range(6)])[:, 0] > 0.5
    predicted = truth.clone()
    predicted[:, :, 0] = True
    for name, rows in (("red", [0, 2, 4]), ("green", [1, 3, 5])):
        m = result.metrics[name]
        assert m["samples"] == 3
        assert m["joints_mean_cm"] == pytest.approx(5.0, abs=1e-4) and m["joints_median_cm"] == pytest.approx(5.0, abs=1e-4)
        assert m["base_mean_cm"] == pytest.approx(2.0, abs=1e-4)
        p, t = predicted[rows], truth[rows]
        assert m["mask_accuracy"] == pytest.approx(float((p == t).float().mean()))
        assert m["mask_iou"] == pytest.approx(float((p & t).sum() / (p | t).sum()))
    assert result.metrics["red"]["type_accuracy"] == pytest.approx(2 / 3)  # sample 0 is a red one, answered wrong
    assert result.metrics["green"]["type_accuracy"] == 1.0
    assert result.metrics["all"]["samples"] == 6
    assert len(result.per_keypoint_cm["red"]) == 3 and len(result.per_keypoint_cm["green"]) == 4
    assert np.allclose(result.per_keypoint_cm["green"], 5.0, atol=1e-4)
    md, js = result.save(tmp_path, title="oracle")
    text = md.read_text()
    assert "| Joint error, median (cm) | 5.00 | 5.00 | 5.00 |" in text and "| Mask IoU |" in text
    assert json.loads(js.read_text())["metrics"]["green"]["samples"] == 3
