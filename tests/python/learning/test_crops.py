"""Zooming into part of an image: resampling against ramps and constants (exact by
linearity), the zoomed intrinsics against projecting and moving pixels, boxes that
hold their points, nearest labels."""

from __future__ import annotations

import numpy as np
import pytest

from earcore.learning.crops import Box, box_around, crop, crop_intrinsics, crop_labels, crop_pixels, resample_matrix, uncrop_pixels

K = np.array([[180.0, 0.0, 127.3], [0.0, 181.0, 105.8], [0.0, 0.0, 1.0]])


def ramp(h, w):
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return 3.0 * u - 2.0 * v + 7.0


@pytest.mark.parametrize("box", [Box(40.3, 30.7, 128.0, 106.0), Box(10.0, 20.0, 64.0, 53.0), Box(0.0, 0.0, 256.0, 212.0), Box(-32.0, -40.0, 384.0, 318.0)])
def test_a_ramp_is_sampled_where_the_pixels_map(box):
    """Linear interpolation, and box averages over whole source pixels, reproduce a
    linear image at the output pixel centres' source positions, inside the image."""
    src = ramp(212, 256)
    out = crop(src, box, (128, 106))
    centres = uncrop_pixels(np.stack(np.meshgrid(np.arange(128), np.arange(106)), -1), box, (128, 106))
    sx, sy = box.scale((128, 106))
    half = (0.5 / min(sx, 1.0), 0.5 / min(sy, 1.0))  # the footprint's half-size when shrinking
    inside = (centres[..., 0] - half[0] >= 0) & (centres[..., 0] + half[0] <= 255) & (centres[..., 1] - half[1] >= 0) & (centres[..., 1] + half[1] <= 211)
    assert inside.mean() > 0.3
    expected = 3.0 * centres[..., 0] - 2.0 * centres[..., 1] + 7.0
    assert np.abs(out - expected)[inside].max() < 1e-3


def test_resampling_keeps_a_constant_and_is_black_beyond_the_edge():
    m = resample_matrix(100, 50, -30.0, 100.0)  # shrinking, the first 15 outputs wholly outside
    assert np.allclose(m[:15].sum(1), 0) and np.allclose(m[16:].sum(1), 1)
    g = resample_matrix(10, 40, 5.0, 10.0)  # growing ×4 from pixel 5 on: half of it past the edge
    sums = g.sum(1)
    assert np.allclose(sums[:20], 1) and np.allclose(sums[22:], 0)
    with pytest.raises(ValueError):
        resample_matrix(10, 5, 0.0, 0.0)


def test_zoomed_intrinsics_project_where_the_pixels_move():
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), rng.uniform(0.8, 3.0, 50)])
    uv = (points @ K.T)[:, :2] / points[:, 2:]
    box = Box(51.2, 17.9, 97.0, 80.3)
    k = crop_intrinsics(K, box, (128, 106))
    zoomed = (points @ k.T)[:, :2] / points[:, 2:]
    assert np.allclose(zoomed, crop_pixels(uv, box, (128, 106)), atol=1e-9)
    assert np.allclose(uncrop_pixels(zoomed, box, (128, 106)), uv, atol=1e-9)


def test_a_bright_pixel_lands_where_crop_pixels_says():
    src = np.zeros((212, 256), np.float32)
    src[100, 140] = 1.0
    box = Box(76.0, 47.0, 128.0, 106.0)  # native scale: a pure shift
    out = crop(src, box, (128, 106))
    v, u = np.unravel_index(np.argmax(out), out.shape)
    assert np.allclose(crop_pixels(np.array([140.0, 100.0]), box, (128, 106)), [u, v])
    labels = np.zeros((212, 256), np.uint8)
    labels[90:110, 130:150] = 3
    zoomed = crop_labels(labels, Box(110.0, 80.0, 64.0, 53.0), (128, 106))  # ×2
    rows, cols = np.nonzero(zoomed == 3)
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (40, 79, 20, 59)
    assert crop_labels(labels, Box(-100.0, -100.0, 64.0, 53.0), (128, 106), outside=9).max() == 9


def test_boxes_hold_their_points_with_the_output_aspect():
    rng = np.random.default_rng(0)
    for _ in range(20):
        uv = rng.uniform(20, 200, (8, 2))
        box = box_around(uv, (256, 212), (128, 106), margin=0.25, min_width=64.0)
        assert box.width / box.height == pytest.approx(128 / 106)
        assert box.width >= 64.0 - 1e-9
        inside = crop_pixels(uv, box, (128, 106))
        assert inside.min() >= -0.5 and inside[:, 0].max() <= 127.5 and inside[:, 1].max() <= 105.5
    assert box_around(np.full((3, 2), np.nan), (256, 212), (128, 106)) == Box.whole(256, 212)


def test_a_box_must_have_a_size_and_a_place():
    for bad in ((0.0, 0.0, 0.0, 10.0), (0.0, 0.0, 10.0, -1.0), (float("nan"), 0.0, 10.0, 10.0), (0.0, float("inf"), 10.0, 10.0)):
        with pytest.raises(ValueError, match="box"):
            Box(*bad)
