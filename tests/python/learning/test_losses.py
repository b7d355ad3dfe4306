"""The papers' losses against values computed by hand."""

from __future__ import annotations

import math

import pytest
import torch

from earcore.learning.losses import base_loss, class_weights, joint_loss, mask_loss, type_loss


def sig(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def test_mask_loss_is_papers_eq3_with_per_batch_class_weights():
    logits = torch.tensor([[[[0.0, 2.0], [-1.0, 3.0]]], [[[1.0, -2.0], [0.5, -0.5]]]])
    target = torch.tensor([[[[1.0, 0.0], [0.0, 1.0]]], [[[0.0, 0.0], [0.0, 1.0]]]])
    # 3 foreground pixels of 8: w_fg = 8/3, w_bg = 8/5 (Eqs. 1-2 over the batch)
    w_fg, w_bg = 8 / 3, 8 / 5
    expected = 0.0
    for x, y in zip(logits.flatten().tolist(), target.flatten().tolist()):
        p = sig(x)
        expected += -w_fg * y * math.log(p) - w_bg * (1 - y) * math.log(1 - p)
    expected /= 8
    assert float(mask_loss(logits, target)) == pytest.approx(expected, rel=1e-6)
    fg, bg = class_weights(target)
    assert float(fg) == pytest.approx(w_fg) and float(bg) == pytest.approx(w_bg)


def test_mask_loss_clips_at_epsilon():
    logits = torch.tensor([[[[100.0, -100.0]]]])  # p = 1 on a background pixel, p = 0 on a foreground one
    target = torch.tensor([[[[0.0, 1.0]]]])
    eps = 1e-6
    expected = (-2.0 * math.log(eps) - 2.0 * math.log(eps)) / 2  # both weights 1/0.5
    assert float(mask_loss(logits, target, eps=eps)) == pytest.approx(expected, rel=1e-6)


def test_class_weights_make_the_all_background_mask_expensive():
    target = torch.zeros(1, 1, 10, 10)
    target[..., :2, :5] = 1  # 10 % foreground
    background = torch.full_like(target, -3.0)  # "nothing here": 90 % pixel accuracy
    half = torch.where(target > 0, torch.tensor(0.5), torch.tensor(-0.5))  # right everywhere, unsure
    assert float(mask_loss(half, target)) < float(mask_loss(background, target))


def test_joint_loss_is_the_mean_unsquared_distance_over_valid_keypoints():
    pred = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [9.0, 9.0, 9.0]], [[0.0, 0.0, 2.0], [0.0, 0.0, 0.0], [1.0, 2.0, 2.0]]])
    true = torch.zeros_like(pred)
    valid = torch.tensor([[True, True, False], [True, False, True]])
    # sample 0: (5 + 1) / 2 = 3; sample 1: (2 + 3) / 2 = 2.5; batch mean 2.75
    assert float(joint_loss(pred, true, valid)) == pytest.approx(2.75, rel=1e-6)
    assert float(joint_loss(pred[:1, :2], true[:1, :2])) == pytest.approx(3.0, rel=1e-6)
    with pytest.raises(ValueError, match="keypoint_valid"):
        joint_loss(pred, true, valid[:, :2])


def test_base_and_type_losses():
    assert float(base_loss(torch.tensor([[3.0, 4.0, 12.0], [1.0, 0.0, 0.0]]), torch.zeros(2, 3))) == pytest.approx((13 + 1) / 2, rel=1e-6)
    logits = torch.tensor([[0.0, math.log(3.0)], [math.log(4.0), 0.0]])
    assert float(type_loss(logits, torch.tensor([1, 1]))) == pytest.approx((-math.log(3 / 4) - math.log(1 / 5)) / 2, rel=1e-6)


def test_a_perfect_prediction_has_finite_gradients():
    pred = torch.zeros(1, 2, 3, requires_grad=True)
    joint_loss(pred, torch.zeros(1, 2, 3)).backward()
    assert torch.isfinite(pred.grad).all()
