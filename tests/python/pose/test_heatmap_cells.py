"""Where the keypoint network's heatmap cells are: cell j of its stride-s heatmap
(strided 3×3 convolutions with "same" padding) is centred on input pixel s·j, and the
soft-argmax decodes a heatmap peaked at one cell to exactly that pixel (not to
s·j + (s-1)/2, the centre of an s×s block, which is 1.5 px off at stride 4)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from earcore.pose.networks import build_network  # noqa: E402

SIZE = 208  # the stride-8 path's receptive field (radius ~95 px) fits around the centre


def _network(stride: int, size: int = SIZE, keypoints: int = 2):
    options = {"input_size": (size, size - 6), "num_keypoints": keypoints, "num_robots": 2, "width": 0.25, "head": 8, "heatmap_stride": stride, "norm": "none"}
    net = build_network("keypoint", options)
    return net.eval()


@pytest.mark.parametrize("stride", [2, 4, 8])
def test_a_heatmap_cell_sees_the_input_around_stride_times_its_index(stride):
    """With positive, symmetric kernels (every weight 1, no bias: ReLU passes all) a
    cell's sensitivity to the input is symmetric about the pixel it is centred on."""
    net = _network(stride, keypoints=1)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.Conv2d):
                m.weight.fill_(1.0 / m.weight[0].numel())
                if m.bias is not None:
                    m.bias.zero_()
    w, h = net.options.input_size
    image = torch.full((1, 3, h, w), 0.5, requires_grad=True)
    fine, _, _ = net._features(image)
    i, j = (h // 2) // stride, (w // 2) // stride  # a cell near the middle
    fine[0, :, i, j].sum().backward()
    g = image.grad[0].sum(0)
    assert g.min() >= 0 and g[0].abs().sum() == 0 and g[:, 0].abs().sum() == 0  # the receptive field stays inside the image
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    weight = g.double() / g.double().sum()
    centre = (float((weight * ys).sum()), float((weight * xs).sum()))
    assert centre == pytest.approx((stride * i, stride * j), abs=1e-3)


@pytest.mark.parametrize("stride", [2, 4, 8])
def test_a_heatmap_peaked_at_one_cell_decodes_to_that_cells_pixel(stride):
    net = _network(stride, size=64)
    w, h = net.options.input_size
    cells_y, cells_x = -(-h // stride), -(-w // stride)  # ceil: "same" padding keeps the last partial cell
    i, j = cells_y - 2, 3
    peak = torch.full((net.K + 1, cells_y, cells_x), -30.0)
    peak[:, i, j] = 30.0
    with torch.no_grad():
        net.heat.weight.zero_()
        net.heat.bias.zero_()
    net.heat.register_forward_hook(lambda module, args, out: peak[None].expand(out.shape[0], -1, -1, -1))
    out = net(torch.rand(2, 3, h, w))
    assert out["pixels"].shape == (2, net.K + 1, 2)
    assert torch.allclose(out["pixels"], torch.tensor([stride * j, stride * i], dtype=torch.float32).expand(2, net.K + 1, 2), atol=1e-4)
