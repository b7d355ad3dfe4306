"""The parts detector's losses (IROS 2018) against values computed by hand and brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from earcore.learning.losses import centroid_distance, part_centroids, pickup_error, soft_iou_error, voronoi_cells


def test_soft_iou_error_by_hand():
    a = torch.tensor([[[[0.5, 1.0], [0.0, 0.25]]]])
    g = torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]]])
    # intersection 0.5 + 1 = 1.5; union (0.5+1-0.5) + (1+1-1) + 0 + 0.25 = 2.25
    assert float(soft_iou_error(a, g)) == pytest.approx(1 - 1.5 / 2.25)
    # activations on a channel the image lacks count against it (all channels together)
    a2 = torch.cat([a, torch.full((1, 1, 2, 2), 0.5)], 1)
    g2 = torch.cat([g, torch.zeros(1, 1, 2, 2)], 1)
    assert float(soft_iou_error(a2, g2)) == pytest.approx(1 - 1.5 / (2.25 + 2.0))
    # a perfect binary prediction: 0; an empty target and no activation: 0; batch mean
    assert float(soft_iou_error(g, g)) == 0.0
    assert float(soft_iou_error(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 2))) == 0.0
    both = soft_iou_error(torch.cat([a, g]), torch.cat([g, g]))
    assert float(both) == pytest.approx((1 - 1.5 / 2.25) / 2)
    with pytest.raises(ValueError, match="differ in shape"):
        soft_iou_error(a, g2)


def test_voronoi_cells_against_brute_force():
    rng = np.random.default_rng(3)
    h, w, m = 7, 9, 5
    points = torch.tensor(rng.uniform(0, 8, (2, m, 2)))
    classes = torch.tensor([[0, 0, 1, 0, 1], [2, 2, 2, 1, 0]])
    valid = torch.tensor([[True, True, True, False, True], [True, True, False, True, True]])
    cells = voronoi_cells(points, classes, valid, h, w).numpy()
    for b in range(2):
        for i in range(m):
            for v in range(h):
                for u in range(w):
                    if not valid[b, i]:
                        want = 0.0
                    else:
                        mine = (u - points[b, i, 0]) ** 2 + (v - points[b, i, 1]) ** 2
                        rivals = [(u - points[b, j, 0]) ** 2 + (v - points[b, j, 1]) ** 2 for j in range(m) if valid[b, j] and classes[b, j] == classes[b, i]]
                        want = float(mine <= min(rivals))
                    assert cells[b, i, v, u] == want


def test_centroid_distance_by_hand():
    # one class, one part: the whole channel's weighted centroid (the paper's definition)
    a = torch.zeros(1, 2, 3, 4)
    a[0, 1, 0, 0] = 1.0  # (u, v) = (0, 0)
    a[0, 1, 2, 3] = 3.0  # (3, 2)
    a[0, 0, 1, 1] = 5.0  # another class: ignored
    points = torch.tensor([[[1.0, 1.0]]])
    classes = torch.tensor([[1]])
    valid = torch.tensor([[True]])
    centre = part_centroids(a, points, classes, valid)
    assert centre[0, 0].tolist() == pytest.approx([9 / 4, 6 / 4], rel=1e-5)
    assert float(centroid_distance(a, points, classes, valid)) == pytest.approx(np.hypot(9 / 4 - 1, 6 / 4 - 1), rel=1e-5)
    # two parts of one class split the channel by their Voronoi cells; invalid slots ignored
    a = torch.zeros(1, 1, 1, 6)
    a[0, 0, 0, :] = torch.tensor([1.0, 1.0, 0.0, 0.0, 2.0, 2.0])
    points = torch.tensor([[[0.0, 0.0], [5.0, 0.0], [2.0, 0.0]]])
    classes = torch.tensor([[0, 0, 0]])
    valid = torch.tensor([[True, True, False]])
    # cells: u <= 2 → part 0 (centroid 0.5), u >= 3 → part 1 (centroid 4.5)
    assert float(centroid_distance(a, points, classes, valid)) == pytest.approx((0.5 + 0.5) / 2, rel=1e-5)
    # no valid part: zero
    assert float(centroid_distance(a, points, classes, torch.zeros(1, 3, dtype=torch.bool))) == 0.0


def test_centroid_distance_gradient_moves_activation_towards_the_point():
    a = torch.full((1, 1, 1, 5), 0.5, requires_grad=True)
    loss = centroid_distance(a, torch.tensor([[[4.0, 0.0]]]), torch.tensor([[0]]), torch.tensor([[True]]))
    loss.backward()
    g = a.grad[0, 0, 0].tolist()
    assert g[0] > 0 > g[4]  # more weight near u = 4 lowers the distance


def test_pickup_error_is_eq4():
    d = torch.tensor([0.0, 1.0, 3.0, 100.0])
    assert pickup_error(d).tolist() == pytest.approx([0.0, 0.5, 0.9, 1e4 / (1e4 + 1)])


def test_vector_spread_on_hand_made_vectors():
    from earcore.learning.losses import vector_spread

    e1, e2 = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])
    diag = torch.tensor([1.0, 1.0]) / math.sqrt(2)
    # two classes along orthogonal axes, each matched with itself: the loss's minimum, 0
    x = torch.stack([e1, e2])
    same = torch.tensor([[True, False], [False, True]])
    assert float(vector_spread(x, x * 3.0, same)) == pytest.approx(0.0, abs=2e-3)  # the length does not count
    # the same vectors with the classes swapped: every pair is wrong, 1
    assert float(vector_spread(x, x, ~same)) == pytest.approx(1.0, abs=2e-3)
    # 45 degrees is half of orthogonal: 0.5 whether or not the classes agree
    assert float(vector_spread(e1[None], diag[None], torch.tensor([[True]]))) == pytest.approx(0.5, abs=1e-4)
    assert float(vector_spread(e1[None], diag[None], torch.tensor([[False]]))) == pytest.approx(0.5, abs=1e-4)
    # a 2 x 3 case by hand: angles (in right angles) 0, 1, 0.5 / 1, 0, 0.5, same = the first of each row
    y = torch.stack([e1, e2, diag])
    s = torch.tensor([[True, False, False], [True, False, True]])
    expected = ((0.0) + (1 - 1.0) + (1 - 0.5) + 1.0 + (1 - 0.0) + 0.5) / 6
    assert float(vector_spread(x, y, s)) == pytest.approx(expected, abs=2e-3)
    # the gradient turns a same-class pair towards each other
    a = torch.tensor([[1.0, 0.2]], requires_grad=True)
    vector_spread(a, e1[None], torch.tensor([[True]])).backward()
    assert a.grad is not None and float(a.grad[0, 1]) > 0  # descending lowers the second component
    with pytest.raises(ValueError, match="same"):
        vector_spread(x, y, same)
